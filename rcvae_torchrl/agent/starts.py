"""Putting a real env in a given start state, so the real agent starts where a forecast did.

A forecast is made from start states; checking it means running the same agent in the real env
from the same states. Three ways, each a ``reset_to_state(env, start) -> tensordict`` function
for :func:`~rcvae_torchrl.agent.run_episodes`, with ``start`` a row of the TensorDict that
:func:`draw_starts` returns:

- :func:`reset_by_seed` (any env whose reset is a function of its seed, e.g. every dm_control
  task): replays the seeded reset that drew the start, and checks that it gives the same
  observation;
- :func:`reset_to_physics` (dm_control and other MuJoCo envs built on a dm_control
  ``Physics``): sets the simulator's state (``qpos``, ``qvel``, ``act`` and the model fields a
  task randomises, e.g. a target's position) inside the task's own episode initialisation, so
  every wrapper and transform sees a normal reset; it can start from any state, not only one a
  reset draws;
- a function of the observation alone, where the observation holds the whole simulator state
  (an env-specific function, such as the example domain's ``reset_to_state``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from rcvae_torchrl._checks import check_seeds
from rcvae_torchrl.data import seed_env

from .episodes import ResetToState, reset_to, seed_episodes

__all__ = [
    "MODEL_FIELDS",
    "draw_starts",
    "observe_starts",
    "physics_of",
    "reset_by_seed",
    "reset_to_physics",
    "start_episodes",
]

#: Model fields a task may randomise per episode (positions, orientations, sizes, masses),
#: captured with the simulator state.
MODEL_FIELDS = (
    "geom_pos",
    "geom_quat",
    "geom_size",
    "body_pos",
    "body_quat",
    "body_mass",
    "site_pos",
    "site_quat",
)


def physics_of(env: EnvBase):
    """The dm_control ``Physics`` inside a TorchRL env (through transforms and wrappers)."""
    base = getattr(env, "base_env", env)
    physics = getattr(getattr(base, "_env", None), "physics", None)
    if physics is None:
        inside = f" over a {type(base).__name__}" if base is not env else ""
        raise TypeError(
            f"env: expected a TorchRL env over a dm_control environment (DMControlEnv or "
            f"DMControlWrapper, possibly transformed), got a {type(env).__name__}{inside}; "
            "for another simulator, pass reset_to_state a function (env, start) -> the env's "
            "reset TensorDict that sets its state; for a SerialEnv or ParallelEnv of dm_control "
            "envs, pass real_outcomes a function that makes one, with workers=K"
        )
    return physics


def _capture_physics(env: EnvBase) -> TensorDict:
    physics = physics_of(env)
    data, model = physics.data, physics.model
    state = {k: torch.as_tensor(np.array(getattr(data, k))) for k in ("qpos", "qvel", "act")}
    state["model"] = {f: torch.as_tensor(np.array(getattr(model, f))) for f in MODEL_FIELDS}
    return TensorDict(state, batch_size=[])


def draw_starts(env: EnvBase, seeds: Sequence[int], *, physics: bool = False) -> TensorDict:
    """Start states drawn by the env's own reset, one per seed.

    Returns a TensorDict ``[B]`` with ``"observation"`` ``[B, S]``, ``"seed"`` ``[B]`` and,
    with ``physics=True`` (dm_control envs), the simulator state under ``"physics"`` for
    :func:`reset_to_physics`. ``env`` is one env (``batch_size=[]``): a batched env's reset
    draws several starts per seed, which no seed can replay one by one.
    """
    _check_one_env(env)
    rows = []
    for seed in check_seeds("seeds", seeds):
        seed_env(env, seed)
        td = env.reset()
        row = {"observation": td["observation"].clone(), "seed": torch.tensor(int(seed))}
        if physics:
            row["physics"] = _capture_physics(env)
        rows.append(TensorDict(row, batch_size=[]))
    if not rows:
        raise ValueError("seeds: expected at least one seed, got none")
    return torch.stack(rows)


def observe_starts(
    env: EnvBase, starts: TensorDictBase, reset_to_state: ResetToState | None = None
) -> TensorDict:
    """``starts`` with each ``"observation"`` the one the env gives when ``reset_to_state``
    (default :func:`reset_to_physics`) puts it in that start.

    For start states made by hand from drawn ones: a state no reset draws (a cartpole's pole
    up or spinning, set in ``starts["physics", "qpos"]`` and ``"qvel"``) needs the observation
    that goes with it, for the forecast made from it and for the real episodes, whose reset is
    refused when its observation is not the start's.

    Example::

        starts = draw_starts(env, seeds=range(30), physics=True)
        starts["physics", "qvel"][:, 1] = 20.0  # the pole spinning at 20 rad/s
        starts = observe_starts(env, starts)
    """
    _check_one_env(env)
    if not isinstance(starts, TensorDictBase) or starts.batch_dims != 1:
        raise TypeError(
            "starts: expected a TensorDict [B] of start states (from draw_starts), got "
            f"{type(starts).__name__}"
            + (f" of batch {list(starts.batch_size)}" if isinstance(starts, TensorDictBase) else "")
        )
    reset_to_state = reset_to_physics if reset_to_state is None else reset_to_state
    try:
        observed = [
            reset_to(reset_to_state, env, starts[i].exclude("observation"))["observation"].clone()
            for i in range(starts.shape[0])
        ]
    except KeyError as error:
        if "observation" not in str(error):
            raise
        raise KeyError(
            "reset_to_state: it reads the start's 'observation', which observe_starts leaves "
            "out: it makes each start's observation from the rest of the start (its physics "
            "state, a seed); a start set by its observation has one already and needs no "
            "observe_starts (pass it to real_outcomes as it is)"
        ) from error
    out = starts.clone()
    out.set("observation", torch.stack(observed).to(out.device))
    return out


def _check_one_env(env: EnvBase) -> None:
    """Start states are drawn and observed one at a time: a batched env's reset would draw
    several per seed."""
    if env.batch_size:
        raise ValueError(
            f"env: expected one env (batch_size []), got batch_size {list(env.batch_size)}; "
            "draw the starts from an env of the same kind unbatched"
        )


def _check_start(start: object, key: str, made_by: str) -> None:
    """One start of :func:`draw_starts` (a tensordict ``[]`` with ``key``)."""
    if not isinstance(start, TensorDictBase) or start.batch_dims or key not in start.keys():
        got = type(start).__name__
        if isinstance(start, TensorDictBase):
            keys = sorted(map(str, start.keys()))
            got = f"a tensordict of batch {tuple(start.batch_size)} and keys {keys}"
        batch = isinstance(start, TensorDictBase) and start.batch_dims
        raise ValueError(
            f"start: expected one start of {made_by} (a tensordict [] with a {key!r} entry), "
            f"got {got}"
            + (
                "; this reset serves one env (batch_size []): for a batched env, pass a "
                "reset_to_state of your own that takes a batch of starts, or a function that "
                "makes one env with workers=K"
                if batch
                else ""
            )
        )


def reset_by_seed(env: EnvBase, start: TensorDictBase) -> TensorDictBase:
    """Reset ``env`` to ``start`` by replaying the seeded reset that drew it.

    The env's random stream then continues from its state after that reset, the same in
    every run from this start: an env that draws its noise from that stream repeats one
    episode in every run (``real_outcomes`` warns of such copies); transforms with their own
    stream (e.g. action noise) keep theirs, so seed those per episode first. Raises
    ``ValueError`` when the reset does not give ``start["observation"]`` (an env whose reset
    is not a function of its seed).
    """
    _check_start(start, "seed", "draw_starts(env, seeds)")
    env.set_seed(int(start["seed"]) % 2**32)  # as draw_starts' seed_env gave it
    td = env.reset()
    if start["observation"].shape != td["observation"].shape:
        raise ValueError(
            f"start['observation']: expected the env's observation shape "
            f"{list(td['observation'].shape)}, got {list(start['observation'].shape)}"
        )
    if not torch.equal(td["observation"], start["observation"].to(td["observation"])):
        raise ValueError(
            f"start: the seeded reset (seed {int(start['seed'])}) did not give the recorded "
            "observation; this env's reset is not a function of its seed: use "
            "reset_to_physics (dm_control) or an env-specific reset_to_state"
        )
    return td


def reset_to_physics(
    env: EnvBase, start: TensorDictBase, *, model_fields: Sequence[str] = MODEL_FIELDS
) -> TensorDictBase:
    """Reset a dm_control-based env and put its simulator in ``start["physics"]``.

    The state is set inside the task's ``initialize_episode`` (after the task's own
    initialisation), so the observation, the wrappers and the transforms all see a regular
    reset. The task's ``after_step`` is called once more (a no-op for most dm_control tasks),
    so tasks that cache what they observe there see the new state. The start's model fields
    (``model_fields``, by default all of :data:`MODEL_FIELDS`: masses, site positions) hold
    for this episode only: the env's next reset, whoever calls it, first puts its own back (a
    heavier arm set for one start does not leak into the starts drawn after it). A patch of
    one's own on the task's ``initialize_episode`` (an instance attribute) is kept, and runs.

    Those fields replace what the task drew for this episode: a start keeps the target or the
    mass it was drawn with. Physics that a task randomises per episode (a mass drawn in its
    ``initialize_episode``: domain randomisation) is then that of the start's draw in every
    run from it, not a new draw per run: leave such fields out, e.g.
    ``functools.partial(reset_to_physics, model_fields=("site_pos",))`` as ``reset_to_state``
    (the task's draw then holds; a start's observation should not depend on it).
    """
    fields = tuple(model_fields)
    unknown = [f for f in fields if f not in MODEL_FIELDS]
    if unknown or isinstance(model_fields, str):
        raise ValueError(
            f"model_fields: expected names among MODEL_FIELDS {list(MODEL_FIELDS)}, got "
            f"{model_fields!r}"
        )
    physics = physics_of(env)  # a clear error for an env without a dm_control physics
    task = getattr(env, "base_env", env)._env.task
    _check_start(start, "physics", "draw_starts(env, seeds, physics=True)")
    state = start["physics"]
    for name in ("qpos", "qvel", "act"):
        value, size = state[name], getattr(physics.data, name).size
        if value.numel() != size or not bool(torch.isfinite(value).all()):
            raise ValueError(
                f"start['physics', {name!r}]: expected {size} finite values, got shape "
                f"{tuple(value.shape)} with {int((~torch.isfinite(value)).sum())} non-finite"
            )
    # a restore of ours still pending (two of these resets in a row): its model is the env's
    # own, and it knows what the task's instance held before it (a patch of the user's)
    current = task.__dict__.get("initialize_episode")
    if getattr(current, "restores_physics", False):
        own, users = current.own, current.users
    else:
        own = {f: np.array(getattr(physics.model, f)).copy() for f in MODEL_FIELDS}
        users = current
    original = users if users is not None else type(task).initialize_episode.__get__(task)

    def put_back_users() -> None:
        if users is None:
            task.__dict__.pop("initialize_episode", None)
        else:
            task.initialize_episode = users

    def restore_then_initialize(physics_) -> None:  # the next reset: the env's own model
        for field in MODEL_FIELDS:
            getattr(physics_.model, field)[:] = own[field]
        put_back_users()
        original(physics_)

    restore_then_initialize.restores_physics = True  # type: ignore[attr-defined]
    restore_then_initialize.own = own  # type: ignore[attr-defined]
    restore_then_initialize.users = users  # type: ignore[attr-defined]

    def initialize(physics_) -> None:
        original(physics_)
        with physics_.reset_context():
            for name in ("qpos", "qvel", "act"):
                getattr(physics_.data, name)[:] = state[name].numpy()
            for field in fields:
                getattr(physics_.model, field)[:] = state["model", field].numpy()
        task.after_step(physics_)  # a no-op for most tasks; refreshes those that cache

    task.initialize_episode = initialize
    try:
        td = env.reset()
    finally:
        task.initialize_episode = restore_then_initialize
    return td


def start_episodes(
    env: EnvBase,
    seeds: Sequence[int],
    starts: torch.Tensor | TensorDictBase,
    reset_to_state: ResetToState,
) -> TensorDictBase:
    """Seed ``env`` for episodes ``seeds`` and put it in their start states: the reset
    tensordict, ready for ``env.rollout(T, policy, auto_reset=False, tensordict=td)``.

    An env with ``batch_size=[]`` takes one seed and one start row; a batched env ``[N]``
    takes ``N`` of each, seeded by :func:`~rcvae_torchrl.agent.seed_episodes`. Then
    ``reset_to_state(env, starts)``.
    """
    seed_episodes(env, seeds)
    return reset_to(reset_to_state, env, starts)
