"""``nn.Module`` attributes holding a callable (possibly an ``nn.Module``) that is not registered."""

from __future__ import annotations

from typing import Any

__all__ = ["UnregisteredAttributes", "callable_attribute"]


class UnregisteredAttributes:
    """Mixin for ``nn.Module`` classes (transforms included) that keep callables as plain attributes.

    ``nn.Module.__setattr__`` registers every ``nn.Module`` value as a submodule before a property
    setter of the same name can run: the value's parameters then land in the owner's
    ``state_dict()``, ``.to()`` moves them, a property getter reading the instance ``__dict__``
    fails (``KeyError``), and a later assignment of a plain function raises a ``TypeError``. The
    attributes named in ``_unregistered`` bypass that registration: they are set with
    ``object.__setattr__``, so a property setter of that name runs if the class defines one
    (validation included) and the value is stored in the instance ``__dict__`` otherwise. Such a
    value (e.g. a learned distance owned by the learner) is not part of ``state_dict()``,
    ``parameters()``, ``.to()``, ``.train()`` or ``.eval()`` of the owner, and reassigning it always
    takes effect. It is shared by :meth:`~torchrl.envs.transforms.Transform.clone` and pickled with
    the owner, like any plain attribute.

    Put the mixin before the ``nn.Module`` base class and list the attribute names in the class
    attribute ``_unregistered``.

    Examples:
        >>> import torch
        >>> from torch import nn
        >>> class Scorer(UnregisteredAttributes, nn.Module):
        ...     _unregistered = ("score_fn",)
        ...
        ...     def __init__(self, score_fn):
        ...         super().__init__()
        ...         self.score_fn = score_fn
        >>> scorer = Scorer(nn.Linear(2, 1))
        >>> list(scorer.state_dict()), len(list(scorer.parameters()))
        ([], 0)
        >>> scorer.score_fn = torch.sum  # a plain callable replaces the module
        >>> scorer.score_fn is torch.sum
        True
    """

    #: Names of the attributes that are never registered as submodules.
    _unregistered: tuple[str, ...] = ()

    def __setattr__(self, name: str, value: Any) -> None:
        if name in type(self)._unregistered:
            modules = self.__dict__.get("_modules")
            if modules is not None:
                modules.pop(name, None)  # a registration made before the mixin was in place
            object.__setattr__(self, name, value)
        else:
            super().__setattr__(name, value)


def callable_attribute(name: str, contract: str, doc: str) -> property:
    """A property holding a callable in the instance ``__dict__``, for a name listed in ``_unregistered``.

    Assignments are checked (``TypeError`` naming ``name`` and the ``contract`` for anything that is not
    callable) and stored under ``"_<name>"``, outside ``nn.Module`` registration.

    Examples:
        >>> import torch
        >>> from torch import nn
        >>> class Scorer(UnregisteredAttributes, nn.Module):
        ...     _unregistered = ("score_fn",)
        ...     score_fn = callable_attribute("score_fn", "(x) -> score", "The scoring function.")
        >>> scorer = Scorer()
        >>> scorer.score_fn = torch.sum
        >>> scorer.score_fn is torch.sum, Scorer.score_fn.__doc__
        (True, 'The scoring function.')
        >>> try:
        ...     scorer.score_fn = 3
        ... except TypeError as err:
        ...     print(err)
        `score_fn` must be callable (x) -> score, got int.
    """
    key = f"_{name}"

    def fget(self):
        return self.__dict__[key]

    def fset(self, value) -> None:
        if not callable(value):
            raise TypeError(f"`{name}` must be callable {contract}, got {type(value).__name__}.")
        self.__dict__[key] = value

    return property(fget, fset, doc=doc)
