"""``reference_engine``: the ant emulating the reference's MuJoCo 2.0 where MuJoCo 3 differs.

MuJoCo 2.0 (the reference's ``mujoco_py`` 2.0.2.8) took the larger of a contact's two geom margins (MuJoCo 3 adds
them) and, before 2.1.2, approximated a capsule's mass and inertia by a solid cylinder of the capsule's radius and
length ``L + r``. With the option every geom of the scene gets a 0.005 margin (0.01 per contact) and every leg body
an explicit ``<inertial>`` of that cylinder. The expected values here are computed independently with numpy from
the capsules of the compiled default model.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest
import torch
from _recipe import recipe_config
from torchrl.envs.utils import check_env_specs
from torchrl_dhrl.envs import (
    MAZES,
    AntAgent,
    GoalSimulation,
    GymGoalEnv,
    get_maze_spec,
    make_env,
    register_env,
    unregister_env,
)
from torchrl_dhrl.envs.simulation import reference_engine_spec

from torchrl_dhrl.factory import make_environment
from torchrl_dhrl.recipe import (
    FORK_MUTABLE_KEYS,
    IMPLIED_WHEN_ABSENT,
    RESUME_MUTABLE_KEYS,
    ConfigError,
    check_resume_config,
    with_implied_keys,
)

# The reference ant's geom density (its XML's default class); the leg radius and fromto are read off the model.
DENSITY = 5.0
ANT_MAZES = [name for name, spec in MAZES.items() if isinstance(spec.agent, AntAgent)]


def _ant_bodies(model: mujoco.MjModel) -> list[int]:
    return [b for b in range(model.nbody) if model.body(b).name.startswith("ant/")]


def _mat(quat) -> np.ndarray:
    out = np.zeros(9)
    mujoco.mju_quat2Mat(out, np.asarray(quat, dtype=np.float64))
    return out.reshape(3, 3)


def _body_inertia_tensor(model: mujoco.MjModel, body: int) -> np.ndarray:
    """The body's inertia tensor about its centre of mass, in the body frame."""
    rot = _mat(model.body_iquat[body])
    return rot @ np.diag(model.body_inertia[body]) @ rot.T


def _capsules(model: mujoco.MjModel) -> list[dict]:
    """Every capsule of the ant: body, radius, endpoints in the body frame (from ``geom_pos``, ``geom_quat`` and
    the half-length ``geom_size[1]``)."""
    out = []
    for g in range(model.ngeom):
        if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_CAPSULE:
            continue
        radius, half = model.geom_size[g, :2]
        axis = _mat(model.geom_quat[g])[:, 2]
        centre = model.geom_pos[g]
        out.append(
            {
                "body": int(model.geom_bodyid[g]),
                "radius": float(radius),
                "ends": (centre - half * axis, centre + half * axis),
            }
        )
    return out


def _mujoco_2_0_capsule(radius: float, start: np.ndarray, end: np.ndarray):
    """Mass, centre and inertia tensor (body frame) of MuJoCo 2.0's cylinder approximation of a capsule."""
    segment = end - start
    length = np.linalg.norm(segment)
    height = length + radius  # the cylindrical section extended by radius / 2 at both ends
    mass = DENSITY * np.pi * radius**2 * height
    axial = mass * radius**2 / 2
    transverse = mass * (3 * radius**2 + height**2) / 12
    u = segment / length
    tensor = transverse * (np.eye(3) - np.outer(u, u)) + axial * np.outer(u, u)
    return mass, (start + end) / 2, tensor


@pytest.fixture(scope="module")
def models():
    spec = get_maze_spec("AntMaze")
    return spec.compile_model(), reference_engine_spec(spec).compile_model()


def test_capsule_masses_and_inertias_are_mujoco_2_0s(models):
    default, reference = models
    capsules = _capsules(default)
    assert len(capsules) == 12  # 4 legs x (fixed segment, hip, ankle)
    bodies = [c["body"] for c in capsules]
    assert len(set(bodies)) == 12  # one capsule per body: its inertial is the capsule's alone
    for capsule in capsules:
        body = capsule["body"]
        assert reference.body(body).name == default.body(body).name
        mass, centre, tensor = _mujoco_2_0_capsule(capsule["radius"], *capsule["ends"])
        assert reference.body_mass[body] == pytest.approx(mass, rel=1e-12)
        np.testing.assert_allclose(reference.body_ipos[body], centre, atol=1e-12)
        np.testing.assert_allclose(_body_inertia_tensor(reference, body), tensor, rtol=1e-9, atol=1e-15)
        # MuJoCo 3's own value, without the option, is the exact capsule (the reference's was lighter)
        length = np.linalg.norm(capsule["ends"][1] - capsule["ends"][0])
        r = capsule["radius"]
        exact = DENSITY * (np.pi * r**2 * length + 4 / 3 * np.pi * r**3)
        assert default.body_mass[body] == pytest.approx(exact, rel=1e-12)
        assert 0.93 < mass / exact < 0.97  # 4-7% lighter


def test_total_mass_is_the_reference_0_879(models):
    default, reference = models
    assert round(float(default.body_mass[_ant_bodies(default)].sum()), 3) == 0.911
    assert round(float(reference.body_mass[_ant_bodies(reference)].sum()), 3) == 0.879


def test_the_inertial_frame_is_aligned_with_each_capsule(models):
    _, reference = models
    for capsule in _capsules(reference):
        body = capsule["body"]
        start, end = capsule["ends"]
        u = (end - start) / np.linalg.norm(end - start)
        frame = _mat(reference.body_iquat[body])
        inertia = reference.body_inertia[body]
        axial = int(np.argmin(inertia))  # the capsule axis carries the smallest moment
        assert abs(frame[:, axial] @ u) == pytest.approx(1.0, abs=1e-12)
        others = [k for k in range(3) if k != axial]
        assert inertia[others[0]] == pytest.approx(inertia[others[1]], rel=1e-12)
        np.testing.assert_allclose(reference.body_ipos[body], (start + end) / 2, atol=1e-12)


def test_the_torso_keeps_its_exact_sphere(models):
    default, reference = models
    torso = default.body("ant/torso").id
    assert reference.body_mass[torso] == default.body_mass[torso]
    np.testing.assert_array_equal(reference.body_inertia[torso], default.body_inertia[torso])
    np.testing.assert_array_equal(reference.body_ipos[torso], default.body_ipos[torso])


@pytest.mark.parametrize("name", ANT_MAZES)
def test_every_scene_geom_has_half_the_margin(name):
    """0.005 on the ant's, the floor's and the walls' geoms: 0.01 per contact (MuJoCo 3 adds the margins)."""
    for engine, margin in ((False, 0.01), (True, 0.005)):
        model = GoalSimulation(name, reference_engine=engine).model
        colliding = (model.geom_contype != 0) | (model.geom_conaffinity != 0)
        assert colliding.sum() > 13  # the 13 ant geoms, the floor and the walls
        np.testing.assert_array_equal(model.geom_margin[colliding], margin)
        floor = model.geom("floor").id
        assert model.geom_margin[floor] == margin


def test_the_default_model_is_unchanged():
    """Off by default everywhere: the shared spec, make_env, the Gymnasium env, and ``False`` explicitly."""
    assert AntAgent().reference_engine is False
    xml = AntAgent().build_mjcf().to_xml_string()
    assert "<inertial" not in xml and 'margin="0.01"' in xml
    for name in ANT_MAZES:
        assert MAZES[name].agent.reference_engine is False
    spec = get_maze_spec("AntMazeBottleneck")
    base = spec.compile_model()
    for model in (
        make_env("AntMazeBottleneck").simulation.model,
        GoalSimulation(spec, reference_engine=False).model,
        GymGoalEnv("AntMazeBottleneck").model,
    ):
        for field in ("body_mass", "body_inertia", "body_ipos", "body_iquat", "geom_margin", "geom_solimp"):
            np.testing.assert_array_equal(getattr(model, field), getattr(base, field), err_msg=field)
    # the option builds another spec (its own cached XML); the shared one is untouched
    assert reference_engine_spec(spec) != spec and spec.agent.reference_engine is False
    assert reference_engine_spec(spec).name == spec.name


def test_the_option_reaches_every_front_end():
    expected = 0.879
    env = make_env("AntMazeSmall", num_envs=2, seed=0, reference_engine=True)
    assert env.task.agent.reference_engine and env.task.name == "AntMazeSmall"
    gym_env = GymGoalEnv("AntMazeSmall", reference_engine=True)
    for model in (env.simulation.model, gym_env.model):
        assert round(float(model.body_mass[_ant_bodies(model)].sum()), 3) == expected
    import gymnasium as gym

    made = gym.make("dhrl/AntMaze-v0", reference_engine=True)
    model = made.unwrapped.model
    assert round(float(model.body_mass[_ant_bodies(model)].sum()), 3) == expected


@pytest.mark.parametrize("name", ["PointMaze", "Reacher3D", "UR3Obstacle"])
def test_refused_for_an_env_without_the_ant(name):
    for build in (
        lambda: make_env(name, reference_engine=True),
        lambda: GoalSimulation(name, reference_engine=True),
        lambda: GymGoalEnv(name, reference_engine=True),
    ):
        with pytest.raises(ValueError, match=rf"reference_engine.*{name}"):
            build()
    make_env(name, reference_engine=False)  # off: nothing to refuse


def test_refused_for_a_registered_env_and_for_a_non_boolean():
    def factory(*, num_envs, seed, device, eval, max_episode_steps):  # noqa: A002
        return make_env("AntMazeSmall", num_envs=num_envs, seed=seed, device=device, eval=eval)

    register_env("RefEngineAnt", factory)
    try:
        with pytest.raises(ValueError, match=r"reference_engine.*'RefEngineAnt'"):
            make_env("RefEngineAnt", reference_engine=True)
    finally:
        unregister_env("RefEngineAnt")
    with pytest.raises(ValueError, match="reference_engine must be True or False"):
        GoalSimulation("AntMaze", reference_engine="yes")


def test_check_env_specs_passes_with_the_option():
    env = make_env("AntMazeBottleneck", num_envs=2, seed=0, reference_engine=True, max_episode_steps=5)
    check_env_specs(env)
    rollout = env.rollout(6, break_when_any_done=False)
    assert rollout["observation"].shape == torch.Size([2, 6, 29])
    assert torch.isfinite(rollout["next", "observation"]).all()


# ---------------------------------------------------------------------------------------------------- recipe
def test_the_recipe_key_defaults_off_and_is_an_experiment_key():
    cfg = recipe_config("env=AntMaze")
    assert cfg["reference_engine"] is False
    assert IMPLIED_WHEN_ABSENT["reference_engine"] is False
    assert "reference_engine" not in RESUME_MUTABLE_KEYS and "reference_engine" not in FORK_MUTABLE_KEYS
    old = {k: v for k, v in cfg.items() if k != "reference_engine"}  # a checkpoint from before the key
    assert with_implied_keys(old)["reference_engine"] is False
    assert check_resume_config(old, cfg) == []
    with pytest.raises(ConfigError, match=r"reference_engine False -> True"):
        check_resume_config(old, {**cfg, "reference_engine": True})


def test_the_recipe_key_reaches_the_env():
    """``reference_engine=true`` builds the training and test envs with the 0.879 ant; the default, and a run saved
    before the key existed, with MuJoCo 3's 0.911."""
    from dhrl_utils import build_environment  # the recipes' folder is on sys.path (``_recipe``)

    cfg = recipe_config("env=AntMazeSmall", "preset=smoke", "reference_engine=true")
    for evaluation in (False, True):
        model = build_environment(cfg, "cpu", eval=evaluation).simulation.model
        assert round(float(model.body_mass[_ant_bodies(model)].sum()), 3) == 0.879
    default = recipe_config("env=AntMazeSmall", "preset=smoke")
    old = with_implied_keys({k: v for k, v in default.items() if k != "reference_engine"})
    for config in (default, old):
        model = build_environment(config, "cpu").simulation.model
        assert round(float(model.body_mass[_ant_bodies(model)].sum()), 3) == 0.911
    model = make_environment("AntMaze", num_envs=1, reference_engine=True).simulation.model
    assert round(float(model.body_mass[_ant_bodies(model)].sum()), 3) == 0.879


def test_reference_engine_spec_is_hashable_and_cached():
    spec = reference_engine_spec("AntMaze")
    assert spec == reference_engine_spec(get_maze_spec("AntMaze"))
    assert hash(spec) == hash(dataclasses.replace(spec))
    assert reference_engine_spec(spec) == spec  # idempotent
