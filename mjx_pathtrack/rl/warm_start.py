"""Warm starts (``--init-from``): a finished run's networks as the start of another run, also when
the new run observes more or drives more joints.

What each network input and output means is named by a :class:`PolicyLayout` (the source's comes
from its ``export/manifest.json``, this run's from its environment). Inputs and outputs are matched
by those names: joints by joint name, the knots by path-joint name, the other observation blocks
by block name. What the source did not have enters so that the warm policy acts exactly as the
source's on everything it knew:

* **new inputs** (a task's sensor blocks; the position, velocity and acceleration of new joints):
  zero weights in both networks' first layers, a unit normaliser (mean 0, std 1);
* **new joints** (actions): a zero mean head and this run's initial log-std; then
  :func:`fit_new_joints` fits the policy so that those joints *hold still* at their start
    position (:func:`hold_actions`) while the source's joints keep the source's actions. The
  middle of the safe acceleration range (action 0) keeps about a joint's velocity, not its
  position, so a policy blind to a new joint lets it drift (ARMAR-4's legs: the robot falls).

Everything else (network sizes, the value network's privileged inputs) must be equal;
:class:`~mjx_pathtrack.config.run_dir.RunDirError` names the first difference.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from mjx_pathtrack.core import limits as L
from mjx_pathtrack.envs import action_prior
from mjx_pathtrack.config.run_dir import RunDirError
from mjx_pathtrack.config.stored import StoredDataError, read_params

#: observation blocks with one entry per actuated joint (:func:`~mjx_pathtrack.deploy.export.observation_layout`)
JOINT_BLOCKS = ("position", "velocity", "acceleration")
KNOTS = "knots"


@dataclasses.dataclass(frozen=True)
class PolicyLayout:
    """What a policy's inputs and outputs mean: ``observation``: the blocks ``({name, start,
    size}, ...)`` of :func:`~mjx_pathtrack.deploy.export.observation_layout`; ``joints``: the
    actuated joints' names, one action each, in order; ``path_joints``: indices into ``joints`` of
    the joints the path covers (the columns of the ``knots`` block, ``[n_next + 1, n_path]``)."""

    observation: tuple[dict, ...]
    joints: tuple[str, ...]
    path_joints: tuple[int, ...]

    @classmethod
    def from_manifest(cls, manifest: dict) -> PolicyLayout | None:
        """The layout an export's manifest records (None if it lacks one: an older export)."""
        if not manifest.get("observation_layout") or not manifest.get("joint_names"):
            return None
        return cls(tuple(manifest["observation_layout"]), tuple(manifest["joint_names"]),
                   tuple(int(i) for i in manifest.get("path_joints", range(len(manifest["joint_names"])))))

    @classmethod
    def of_env(cls, env, joint_names) -> PolicyLayout:
        """The layout of a path-tracking environment whose actuated joints are ``joint_names``."""
        from mjx_pathtrack.deploy.export import env_observation_layout

        return cls(tuple(env_observation_layout(env)), tuple(joint_names), tuple(int(i) for i in env.path_joints))

    @property
    def size(self) -> int:
        last = self.observation[-1]
        return int(last["start"] + last["size"])

    @property
    def path_names(self) -> tuple[str, ...]:
        return tuple(self.joints[i] for i in self.path_joints)


def _positions(names, of, what: str) -> np.ndarray:
    """Index in ``of`` of every name in ``names`` (-1: new); every name of ``of`` must be kept."""
    lost = [n for n in of if n not in names]
    if lost:
        raise RunDirError(f"--init-from: the source run's {what} {lost} are not in this run's; a warm start keeps "
                          f"everything the source policy knew")
    return np.array([of.index(n) if n in of else -1 for n in names], np.int64)


def input_index(source: PolicyLayout, target: PolicyLayout) -> np.ndarray:
    """``[target.size]`` int: for each of this run's observation entries, the source's entry
    with the same meaning, or -1 where the source had none."""
    theirs = {b["name"]: b for b in source.observation}
    lost = [name for name in theirs if name not in {b["name"] for b in target.observation}]
    if lost:
        raise RunDirError(f"--init-from: the source run observes {lost}, this run does not")
    out = np.full(target.size, -1, np.int64)
    for block in target.observation:
        name, start, size = block["name"], int(block["start"]), int(block["size"])
        if name not in theirs:
            continue
        src = theirs[name]
        if name in JOINT_BLOCKS:
            rows = _positions(target.joints, source.joints, "joints")
            out[start:start + size] = np.where(rows >= 0, int(src["start"]) + rows, -1)
        elif name == KNOTS:
            cols = _positions(target.path_names, source.path_names, "path joints")
            knots_t, knots_s = size // max(len(cols), 1), int(src["size"]) // max(len(source.path_joints), 1)
            if knots_t != knots_s:
                raise RunDirError(f"--init-from: the source run observes {knots_s} knots, this run {knots_t} "
                                  f"(another n_next)")
            k = np.arange(knots_t)[:, None]
            out[start:start + size] = np.where(cols >= 0, int(src["start"]) + k * len(source.path_joints) + cols,
                                               -1).reshape(-1)
        else:
            if int(src["size"]) != size:
                raise RunDirError(f"--init-from: observation block {name!r} has {src['size']} entries in the source "
                                  f"run, {size} here")
            out[start:start + size] = int(src["start"]) + np.arange(size)
    return out


def action_index(source: PolicyLayout, target: PolicyLayout) -> np.ndarray:
    """``[n_joints]`` int: for each of this run's actions (joints), the source's, or -1 (new joint)."""
    return _positions(target.joints, source.joints, "joints")


def _gather(theirs, index: np.ndarray, axis: int, fill) -> jax.Array:
    """``theirs`` re-indexed along ``axis`` by ``index`` (-1: ``fill``, a scalar or an array of the result's shape)."""
    taken = jnp.take(jnp.asarray(theirs), jnp.asarray(np.maximum(index, 0)), axis=axis)
    new = np.expand_dims(index < 0, tuple(i for i in range(taken.ndim) if i != axis % taken.ndim))
    return jnp.where(jnp.asarray(new), jnp.asarray(fill, taken.dtype), taken)


def transfer(own, loaded, inputs: np.ndarray | None, actions: np.ndarray | None, source_size: int | None,
             where: str):
    """The source's ``loaded = (normalizer, policy, value)`` parameters in the structure of ``own``
    (this run's freshly initialised ones, single device): inputs re-indexed by ``inputs`` (the
    source's observation has ``source_size`` entries; the value network's privileged features
    after the observation are kept in order), actions by ``actions`` (None: unchanged), new entries
    filled as the module describes. ``where``: the source file, for errors."""
    own_leaves, own_tree = jax.tree.flatten_with_path(own)
    new_leaves = jax.tree.leaves(loaded)
    if len(new_leaves) != len(own_leaves):
        raise RunDirError(f"--init-from: {where} holds {len(new_leaves)} arrays, this run's networks "
                          f"{len(own_leaves)}: another network layout")
    count = float(int(loaded[0].count))  # observations the source's normaliser has seen (brax's UInt64)
    out = []
    for (path, mine), theirs in zip(own_leaves, new_leaves):
        part = ("observation normaliser", "policy", "value")[path[0].idx]
        name = jax.tree_util.keystr(path[1:])
        theirs = jnp.asarray(theirs, mine.dtype)
        first_layer = part == "observation normaliser" or name.endswith("['hidden_0']['kernel']")
        if inputs is not None and first_layer and theirs.ndim >= 1:
            tail = mine.shape[0] - len(inputs)  # the privileged critic's features (0 for the policy)
            if tail >= 0 and theirs.shape[0] - tail == source_size:
                index = np.concatenate([inputs, source_size + np.arange(tail)])
                fill = (1.0 if name.endswith("std") else count if name.endswith("summed_variance") else 0.0) \
                    if part == "observation normaliser" else 0.0
                theirs = _gather(theirs, index, 0, fill)
        elif actions is not None and part == "policy" and "Dense_0" in name:  # the mean head: zero for new joints
            theirs = _gather(theirs, actions, -1, 0.0)
        elif actions is not None and part == "policy" and "std" in name and theirs.ndim == 1:
            theirs = _gather(theirs, actions, 0, mine)
        if theirs.shape != mine.shape:
            raise RunDirError(f"--init-from: {where}: {part} parameter {name} has shape {tuple(theirs.shape)}, this "
                              f"run's {tuple(mine.shape)} (network, observation or action size differ)")
        out.append(theirs)
    return jax.tree.unflatten(own_tree, out)


def read_source(source: str | Path, allow_pickle: bool = False) -> tuple[tuple, PolicyLayout | None, Path]:
    """``((normalizer, policy, value), layout, file)`` of the finished run in directory ``source``
    (its parameters as data; an older run's pickle only with ``allow_pickle``)."""
    try:
        loaded, file = read_params(source, allow_pickle)
    except (OSError, StoredDataError) as e:
        raise RunDirError(f"--init-from: {e}") from e
    manifest = Path(source) / "export" / "manifest.json"
    layout = PolicyLayout.from_manifest(json.loads(manifest.read_text())) if manifest.is_file() else None
    return loaded, layout, file


def warm_start(learner, source: str | Path, devices: int, layout: PolicyLayout | None = None,
               allow_pickle: bool = False):
    """``(learner, new_joints)``: ``learner`` with the policy, value and observation-normaliser
    parameters of the finished run in directory ``source`` (its ``params.msgpack``), matched to this
    run's ``layout`` by name (module docstring; without a layout on either side the shapes must be
    equal), replicated over ``devices``; the optimiser state, environments and keys stay
    ``learner``'s. ``new_joints``: indices of this run's joints the source did not drive (their
    mean action is 0: see :func:`fit_new_joints`)."""
    loaded, theirs, file = read_source(source, allow_pickle)
    own = (learner.normalizer_params, learner.params.policy, learner.params.value)
    if devices > 1:
        own = jax.tree.map(lambda x: x[0], own)
    inputs = actions = None
    if theirs is not None and layout is not None and theirs != layout:
        inputs, actions = input_index(theirs, layout), action_index(theirs, layout)
    normalizer, policy, value = transfer(own, loaded, inputs, actions, theirs.size if theirs else None,
                                         str(file))
    if devices > 1:
        normalizer, policy, value = jax.tree.map(lambda x: jnp.broadcast_to(x, (devices,) + x.shape),
                                                 (normalizer, policy, value))
    learner = learner._replace(normalizer_params=normalizer, params=learner.params.replace(policy=policy, value=value))
    new = np.flatnonzero(actions < 0) if actions is not None else np.zeros(0, np.int64)
    return learner, new


#: natural frequency [rad/s] of the critically damped hold (:func:`hold_actions`). A fit error
#: e of the action holds a joint off by about e A / omega^2 (A: its acceleration limit), so a
#: stiffer hold forgives more; on ARMAR-4's legs (A 3 rad/s^2, ankle roll +-0.025 rad) row 2's
#: policy with the fitted legs fell in 37 % of 128 episodes at 3 rad/s (2 rounds of 3000
#: iterations), in 11 % at 5 (3 rounds of 8000, the defaults of :func:`fit_new_joints`).
HOLD_OMEGA = action_prior.HOLD_OMEGA


def hold_actions(env, track, omega: float = HOLD_OMEGA) -> jax.Array:
    """Actions ``[..., n]`` that hold every joint of ``env`` at its start position ``env.home``
    (:func:`~mjx_pathtrack.core.limits.hold_action` of the state ``track``)."""
    return L.hold_action(env.limits, track.p, track.v, track.a, env.config.dt, env.home, omega)


def fit_new_joints(make_policy, learner, env, new_joints: np.ndarray, devices: int, key, *, n_envs: int = 256,
                   n_steps: int = 40, explore: float = 0.2, rounds: int = 3, iterations: int = 8000,
                   batch: int = 1024, learning_rate: float = 1e-3) -> tuple:
    """Fit the warm policy so that the joints ``new_joints`` hold still (their :func:`hold_actions`)
    and every other joint keeps the warm policy's action, by regression of the policy mean on
    states of ``env``. ``rounds`` of data (DAgger): each ``n_envs`` episodes of ``n_steps``
    decision steps, the first driven by the warm policy with the new joints on their hold actions,
    the later ones by the policy fitted so far (the states its own errors lead to); the new joints'
    actions get Gaussian noise of std ``explore`` so that the fit also covers moving joints. After
    each round, Adam for ``iterations`` steps of ``batch`` states on all data so far. Returns
    ``(learner, report)``: ``states`` fitted on, RMS action errors on the old and new joints on
    them before and after (``rms_old_before`` ... ``rms_new_after``)."""
    import optax

    new = np.zeros(env.action_size, bool)
    new[np.asarray(new_joints, np.int64)] = True
    normalizer, policy = learner.normalizer_params, learner.params.policy
    if devices > 1:
        normalizer, policy = jax.tree.map(lambda x: x[0], (normalizer, policy))
    warm = policy

    def mean_action(policy_params, obs):
        return make_policy((normalizer, policy_params), deterministic=True)(obs, None)[0]

    reset, step = jax.vmap(env.reset), jax.vmap(env.step)

    @jax.jit
    def collect(driver, use_hold, key):
        """States ``[n_envs * n_steps, obs]``, targets, alive mask of episodes driven by ``driver``
        (``use_hold``: the new joints by their hold actions)."""
        key_reset, key_noise = jax.random.split(key)

        def one(state, k):
            obs = state.obs
            hold = hold_actions(env, state.pipeline_state)
            driven = mean_action(driver, obs)
            act = jnp.where(new, jnp.where(use_hold, hold, driven) + explore * jax.random.normal(k, hold.shape), driven)
            target = jnp.where(new, hold, mean_action(warm, obs))
            return step(state, jnp.clip(act, -1.0, 1.0)), (obs, target, state.done == 0)

        state = reset(jax.random.split(key_reset, n_envs))
        _, out = jax.lax.scan(one, state, jax.random.split(key_noise, n_steps))
        return jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), out)

    optimizer = optax.adam(learning_rate)

    def loss(params, obs, target, alive):
        err = jnp.sum((mean_action(params, obs) - target) ** 2, axis=-1)
        return jnp.sum(alive * err) / jnp.maximum(jnp.sum(alive), 1.0) / target.shape[-1]

    @jax.jit
    def fit(params, obs, target, alive, key):
        def update(carry, k):
            params, opt = carry
            rows = jax.random.randint(k, (batch,), 0, obs.shape[0])
            grads = jax.grad(loss)(params, obs[rows], target[rows], alive[rows])
            updates, opt = optimizer.update(grads, opt)
            return (optax.apply_updates(params, updates), opt), None

        (params, _), _ = jax.lax.scan(update, (params, optimizer.init(params)), jax.random.split(key, iterations))
        return params

    def rms(params, obs, target, alive):
        err = np.asarray((mean_action(params, obs) - target) ** 2)[np.asarray(alive)]
        return (float(np.sqrt(err[:, ~new].mean())) if (~new).any() else 0.0, float(np.sqrt(err[:, new].mean())))

    # the first round's driver: the warm policy with the new joints on their hold actions (a
    # policy whose new joints' mean is 0 would drift away); later rounds: the policy fitted so far
    data, fitted = None, warm
    keys = jax.random.split(key, 2 * rounds)
    for r in range(rounds):
        more = collect(warm if r == 0 else fitted, jnp.asarray(r == 0), keys[2 * r])
        data = more if data is None else jax.tree.map(lambda a, b: jnp.concatenate([a, b]), data, more)
        obs, target, alive = data
        fitted = fit(fitted, obs, target, alive.astype(jnp.float32), keys[2 * r + 1])
    obs, target, alive = data
    before, after = rms(warm, obs, target, alive), rms(fitted, obs, target, alive)
    if devices > 1:
        fitted = jax.tree.map(lambda x: jnp.broadcast_to(x, (devices,) + x.shape), fitted)
    report = dict(states=int(np.sum(np.asarray(alive))), rms_old_before=before[0], rms_new_before=before[1],
                  rms_old_after=after[0], rms_new_after=after[1])
    return learner._replace(params=learner.params.replace(policy=fitted)), report
