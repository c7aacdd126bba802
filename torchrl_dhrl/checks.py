"""Argument checks declared on a constructor: run by it on every call, and runnable without building it.

A component states the accepted values of its hyperparameters once, next to its signature::

    class SubgoalScheduler(...):
        @checked(interval=integer(1, what="the high-level interval"))
        def __init__(self, interval, *, goal_dim=None, ...):
            ...

The constructor then raises a :class:`ValueError` naming the argument (``"`interval` (the high-level interval)
must be an integer >= 1, got 0."``) before it builds anything, and :func:`check_arguments` runs the same checks
on a mapping of arguments without building: a pipeline (the recipe does) checks a whole configuration that way
before it builds or writes anything, and renames the arguments after its own keys.
"""

from __future__ import annotations

import functools
import inspect
import numbers
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch

__all__ = [
    "ArgumentCheck",
    "argument_names",
    "check_arguments",
    "checked",
    "choice",
    "flag",
    "indices",
    "integer",
    "layer_sizes",
    "number",
    "vector",
]


class ArgumentCheck:
    """The accepted values of one argument: calling it with ``(name, value)`` raises a :class:`ValueError`
    ``"`name` must be <description>, got <value>."`` for any other value.

    Args:
        accepts (callable): ``value -> bool``.
        description (str): what is accepted, e.g. ``"a number >= 0"``.

    Keyword Args:
        optional (bool): ``None`` is accepted too. Defaults to ``False``.
        what (str, optional): what the argument is, said in parentheses after its name.

    Examples:
        >>> check = ArgumentCheck(lambda v: v in (1, 2), "1 or 2")
        >>> check("k", 2)
        >>> try:
        ...     check("k", 3)
        ... except ValueError as err:
        ...     print(err)
        `k` must be 1 or 2, got 3.
    """

    def __init__(
        self, accepts: Callable[[Any], bool], description: str, *, optional: bool = False, what: str | None = None
    ) -> None:
        self.accepts = accepts
        self.description = f"None or {description}" if optional else description
        self.optional = optional
        self.what = what

    def __call__(self, name: str, value: Any) -> None:
        if value is None and self.optional:
            return
        if not self.accepts(value):
            what = f" ({self.what})" if self.what else ""
            raise ValueError(f"`{name}`{what} must be {self.description}, got {value!r}.")

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.description!r})"


def _reals(value: Any) -> list[float] | None:
    """``value``'s entries as floats (a real number, or a non-empty real tensor), else ``None``."""
    if isinstance(value, bool):
        return None
    if isinstance(value, numbers.Real):
        return [float(value)]
    if isinstance(value, torch.Tensor) and value.numel() and (value.is_floating_point() or value.dtype != torch.bool):
        if value.is_complex():
            return None
        return value.detach().flatten().double().tolist()
    return None


def number(
    low: float | None = None,
    high: float | None = None,
    *,
    low_open: bool = False,
    high_open: bool = False,
    optional: bool = False,
) -> ArgumentCheck:
    """A real number (or a tensor of them, every entry checked) in ``[low, high]``; ``low_open`` / ``high_open``
    exclude the bound. ``None`` bounds are unbounded.

    Examples:
        >>> number(0.0, 1.0, low_open=True, high_open=True).description
        'a number in (0, 1)'
        >>> number(0.0, low_open=True).description, number(0.0).description
        ('a number > 0', 'a number >= 0')
    """
    if low is not None and high is not None:
        text = f"a number in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
    elif low is not None:
        text = f"a number {'>' if low_open else '>='} {low:g}"
    elif high is not None:
        text = f"a number {'<' if high_open else '<='} {high:g}"
    else:
        text = "a number"

    def accepts(value: Any) -> bool:
        values = _reals(value)
        if values is None:
            return False
        for v in values:
            if v != v:  # NaN
                return False
            if low is not None and (v <= low if low_open else v < low):
                return False
            if high is not None and (v >= high if high_open else v > high):
                return False
        return True

    return ArgumentCheck(accepts, text, optional=optional)


def integer(low: int | None = None, *, optional: bool = False, what: str | None = None) -> ArgumentCheck:
    """An integer (not a bool) ``>= low``; ``what`` as :class:`ArgumentCheck`'s.

    Examples:
        >>> integer(1).description
        'an integer >= 1'
        >>> try:
        ...     integer(1, what="the high-level interval")("interval", 0)
        ... except ValueError as err:
        ...     print(err)
        `interval` (the high-level interval) must be an integer >= 1, got 0.
    """

    def accepts(value: Any) -> bool:
        return (
            isinstance(value, numbers.Integral)
            and not isinstance(value, bool)
            and (low is None or value >= low)
        )

    text = "an integer" + ("" if low is None else f" >= {low}")
    return ArgumentCheck(accepts, text, optional=optional, what=what)


def choice(choices: Sequence[Any]) -> ArgumentCheck:
    """One of ``choices``.

    Examples:
        >>> choice(("linear", "softplus")).description
        "one of ('linear', 'softplus')"
    """
    choices = tuple(choices)
    return ArgumentCheck(lambda value: any(value is c or (type(value) is type(c) and value == c) for c in choices),
                         f"one of {choices}")


def flag(*, optional: bool = False) -> ArgumentCheck:
    """``True`` or ``False`` (no other truthy value); with ``optional``, ``None`` too."""
    if optional:
        return ArgumentCheck(lambda value: value is None or isinstance(value, bool), "None, True or False")
    return ArgumentCheck(lambda value: isinstance(value, bool), "True or False")


def indices(*, optional: bool = False, non_empty: bool = False) -> ArgumentCheck:
    """Distinct non-negative integers (a list or tuple; with ``non_empty``, at least one), e.g. positions in an
    observation; with ``optional``, ``None`` too.

    Examples:
        >>> indices(optional=True).description
        'None or a list of distinct integers >= 0'
        >>> try:
        ...     indices()("goal_indices", [0, 0])
        ... except ValueError as err:
        ...     print(err)
        `goal_indices` must be a list of distinct integers >= 0, got [0, 0].
    """

    def accepts(value: Any) -> bool:
        return (
            isinstance(value, Sequence)
            and not isinstance(value, str)
            and (len(value) > 0 or not non_empty)
            and all(isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= 0 for v in value)
            and len(set(value)) == len(value)
        )

    text = f"a {'non-empty ' if non_empty else ''}list of distinct integers >= 0"
    return ArgumentCheck(accepts, text, optional=optional)


def layer_sizes() -> ArgumentCheck:
    """A sequence of positive integers (hidden layer widths; empty: no hidden layer)."""

    def accepts(value: Any) -> bool:
        return (
            isinstance(value, Sequence)
            and not isinstance(value, str)
            and all(isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= 1 for v in value)
        )

    return ArgumentCheck(accepts, "a list of positive integers")


def vector() -> ArgumentCheck:
    """A list of real numbers, or a 1-D real tensor."""

    def accepts(value: Any) -> bool:
        if isinstance(value, torch.Tensor):
            return value.ndim == 1 and _reals(value) is not None
        return (
            isinstance(value, Sequence)
            and not isinstance(value, str)
            and all(_reals(v) is not None and not isinstance(v, torch.Tensor) for v in value)
        )

    return ArgumentCheck(accepts, "a list of numbers")


def _parameter_names(fn: Callable) -> tuple[str, ...]:
    return tuple(inspect.signature(fn).parameters)


def checked(*relations: Callable[..., None], **checks: ArgumentCheck) -> Callable:
    """Declares the checks of a function's (or an ``__init__``'s) arguments; they run before its body.

    Args:
        *relations (callable): checks of several arguments together, called with the arguments their
            parameters name (e.g. ``def box(subgoal_low, subgoal_high): ...``), after the per-argument checks;
            they raise :class:`ValueError` naming the arguments in backquotes.
        **checks (ArgumentCheck): one per argument name.

    The decorated function's ``__argument_checks__`` runs them on a mapping of argument values (the ones it
    holds; a relation runs only when it holds all of its arguments): see :func:`check_arguments`.

    Examples:
        >>> def ordered(low, high):
        ...     if low >= high:
        ...         raise ValueError(f"`low` must be below `high`, got {low}, {high}.")
        >>> @checked(ordered, low=number(), high=number())
        ... def interval_width(low, high):
        ...     return high - low
        >>> interval_width(1.0, 3.0)
        2.0
        >>> try:
        ...     interval_width(3.0, 1.0)
        ... except ValueError as err:
        ...     print(err)
        `low` must be below `high`, got 3.0, 1.0.
    """

    def decorate(fn: Callable) -> Callable:
        signature = inspect.signature(fn)
        names = set(checks) | {name for relation in relations for name in _parameter_names(relation)}
        missing = names - signature.parameters.keys()
        if missing:
            raise TypeError(f"checked: {fn.__qualname__} has no argument {', '.join(sorted(missing))}.")

        def run(arguments: Mapping[str, Any]) -> None:
            for name, check in checks.items():
                if name in arguments:
                    check(name, arguments[name])
            for relation in relations:
                wanted = _parameter_names(relation)
                if all(name in arguments for name in wanted):
                    relation(**{name: arguments[name] for name in wanted})

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            bound = signature.bind(*args, **kwargs)
            bound.apply_defaults()
            run(bound.arguments)
            return fn(*args, **kwargs)

        wrapper.__argument_checks__ = run
        return wrapper

    return decorate


def _function(target: Callable) -> Callable:
    return target.__init__ if isinstance(target, type) else target


def argument_names(target: Callable) -> tuple[str, ...]:
    """The keyword-passable argument names of a class's constructor or of a function (``self`` aside).

    Examples:
        >>> argument_names(number)
        ('low', 'high', 'low_open', 'high_open', 'optional')
    """
    parameters = inspect.signature(_function(target)).parameters.values()
    return tuple(
        p.name
        for p in parameters
        if p.name != "self" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
    )


def check_arguments(target: Callable, arguments: Mapping[str, Any]) -> None:
    """Runs the checks :func:`checked` declared on ``target`` (a class or a function) on ``arguments`` and on
    the defaults of the others, without calling it.

    Arguments without a default that ``arguments`` lacks (e.g. sizes read from an env) are not checked,
    nor the relations that involve them.

    Raises:
        TypeError: an argument ``target`` does not take.
        ValueError: as ``target`` itself would, before building anything.

    Examples:
        >>> from torchrl_dhrl.planner import LandmarkGraph
        >>> try:
        ...     check_arguments(LandmarkGraph, {"cutoff": 0.0})
        ... except ValueError as err:
        ...     print(err)
        `cutoff` must be a number > 0, got 0.0.
    """
    fn = _function(target)
    parameters = inspect.signature(fn).parameters
    unknown = [name for name in arguments if name not in argument_names(target)]
    if unknown:
        raise TypeError(
            f"{getattr(target, '__qualname__', target)} takes no argument {', '.join(map(repr, unknown))}."
        )
    full = {
        name: p.default
        for name, p in parameters.items()
        if name != "self" and p.default is not inspect.Parameter.empty
    }
    full.update(arguments)
    run = getattr(fn, "__argument_checks__", None)
    if run is not None:
        run(full)
