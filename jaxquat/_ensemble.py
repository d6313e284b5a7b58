"""Large ensembles: many bodies at once, sharded over all devices, time processed in chunks.

An ensemble is a batch of independent bodies. The body axis is flattened, padded to a multiple of the
device count and sharded over a one-axis device `Mesh` with JAX's own `NamedSharding`; every step is
element-wise over bodies, so XLA runs each device's share without communication. Time is processed in
chunks: each chunk is one compiled call (a `lax.scan`, no host round-trip inside), and the host only
acts between chunks (progress, writing saved states to disk). Memory is therefore bounded by
bodies × chunk, whatever the number of steps.

Several hosts: call `jax.distributed.initialize()` on every process before anything else; then
`jax.devices()` lists all devices of all hosts and `simulate_ensemble` shards over them. Every process
calls it with the same arguments (e.g. initial conditions made from the same seed).
"""

from __future__ import annotations

import collections
import contextlib
import errno
import json
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from functools import partial, wraps
from tokenize import TokenError
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, ArrayLike

from ._algebra import conjugate
from ._dynamics import (
    _check_inertia as _check_rigid_inertia,
    _rigid_body_field,
    body_step,
    compensations,
)
from ._integrate import (
    LIE_METHODS,
    METHODS,
    Sampled,
    _act,
    _check_magnus_omega,
    _compensated_add,
    _compensated_step,
    _eps_of,
    _reads_time,
    _rotation_minus_one,
    check_times_advance,
    lie_step,
    scan_steps,
)
from ._numerics import (
    as_float_array,
    check_callable,
    check_choice,
    check_frame,
    check_trailing,
    integer_value,
    is_tracer,
    reusable_callable,
    safe_norm,
    static_key,
)
from ._rotation import from_rotvec, rotate_unchecked
from ._sharding import explicit_mesh

_BODY_AXIS = "bodies"
_FORMAT = "jaxquat-ensemble"
_FORMAT_VERSION = 1
# Default chunk length: about this many body-steps per chunk (≈ 0.1–1 s of work on one CPU core),
# so that progress is reported often and memory stays bounded ...
_BODY_STEPS_PER_CHUNK = 2**26
# ... and at most this many saved states per chunk (256 MB of float32 quaternions; a chunk's states
# are on the host while the next chunk computes): with K = save_every < 4 the chunk is shortened to
# 2**24·K/N steps. At 10⁶ bodies, K = 1, streamed, this took the peak memory from 2.4 GB to 1.1 GB
# at the same speed (the run is bound by writing the states).
_SAVED_STATES_PER_CHUNK = 2**24
# As `integrate`: renormalise every this many (global) steps.
_RENORMALIZE_EVERY = 1000
_UNROLL = 1


class EnsembleResult(eqx.Module):
    """The outcome of `simulate_ensemble`.

    Arrays keep the ensemble's batch shape `batch` (the broadcast leading shape of `q0` and `omega`) and
    stay on the devices, sharded over bodies (`result.sharding`) when the number of bodies is a multiple
    of the device count: each device keeps the bodies it computed. For a batch of several axes that is
    a sharding of the leading axes whole and then one evenly (on 4 devices `(8, 3)` over axis 0,
    `(2, 4)` and `(2, 6)` over both on a 2 × 2 mesh with axes `"bodies"`, `"bodies_1"`); where the
    blocks of the flattened bodies are no such product (`(3, 4)` on 4 devices: blocks of 3 bodies
    straddle the rows) the results are replicated. Otherwise the padding bodies are dropped at the end
    and JAX, which needs even shards, lays the (unpadded) results out replicated; choose a multiple of
    the device count (and a leading batch axis that splits evenly) to keep them sharded.

    **Fields:**

    - `final`: orientations after `num_steps` steps, `(*batch, 4)`.
    - `final_omega`: angular velocities after the last step, `(*batch, 3)` (in the frame the ensemble
      was run in); for a kinematic ensemble with constant ω this is ω itself.
    - `saved`: states every `save_every` steps, time-major `(num_saved, *batch, 4)` including the
      initial state; `None` when nothing was saved or the states were streamed to `path`.
    - `saved_omega`: for a rigid-body ensemble, ω at the same times, `(num_saved, *batch, 3)`.
    - `times`: the times of the saved states, `(num_saved,)` (NumPy float64; a JAX array when `dt`
      or `t0` is traced), or `None`.
    - `angle_from_start`: the angle between each body's initial and final orientation, in `[0, π]`.
    - `total_angle`: with `statistics=True`, each body's accumulated rotation angle
      Σₖ angle(q_k, q_{k+1}) over all steps, each the geodesic angle in [0, π] (for constant ω:
      |ω|·T while |ω|Δt ≤ π; a step of |ω|Δt > π counts as 2π − |ω|Δt), else `None`.
    - `max_angle_from_start`: with `statistics=True`, the largest angle from the initial orientation
      over all steps, else `None`.
    - `num_steps`, `num_chunks`, `path`, `seconds` (wall-clock time of the run, compile included).
    """

    final: Array
    final_omega: Array
    saved: Array | None
    saved_omega: Array | None
    times: np.ndarray | None
    angle_from_start: Array
    total_angle: Array | None
    max_angle_from_start: Array | None
    num_steps: int = eqx.field(static=True)
    num_chunks: int = eqx.field(static=True)
    path: str | None = eqx.field(static=True)
    seconds: float = eqx.field(static=True)

    @property
    def sharding(self):
        """The sharding of `final` (over the device mesh's `"bodies"` axis, and `"bodies_1"` for a batch
        split over two axes)."""
        return self.final.sharding

    @property
    def throughput(self) -> float:
        """Body-steps per second of wall-clock time (compile time included)."""
        bodies = math.prod(self.final.shape[:-1])
        return bodies * self.num_steps / max(self.seconds, 1e-12)


def _to_body(omega_world: Array, q: Array) -> Array:
    return rotate_unchecked(omega_world, conjugate(q))


def _to_world(omega_body: Array, q: Array) -> Array:
    return rotate_unchecked(omega_body, q)


def _relative_parts(p: Array, q: Array) -> tuple[Array, Array]:
    """w and |vec|² of r = p* ⊗ q, component by component (XLA:CPU vectorises this over the bodies;
    `multiply` and a sum over the last axis of the `(N, 4)` layout cost about twice as much).

    vec(p* ⊗ q) = vec(p* ⊗ d) with d = q − p (p* ⊗ p is real): exactly 0 when q = p, however the
    compiler contracts the products into fused multiply-adds, and free of cancellation for the
    small steps of a trajectory (the product form left 5e-17 rad a step for a body at rest)."""
    pw, px, py, pz = (p[..., i] for i in range(4))
    qw, qx, qy, qz = (q[..., i] for i in range(4))
    w = pw * qw + px * qx + py * qy + pz * qz
    dw, dx, dy, dz = qw - pw, qx - px, qy - py, qz - pz
    x = pw * dx - dw * px - (py * dz - pz * dy)
    y = pw * dy - dw * py - (pz * dx - px * dz)
    z = pw * dz - dw * pz - (px * dy - py * dx)
    return w, x * x + y * y + z * z


def _angle_of(w: Array, s2: Array) -> Array:
    """2 atan2(|vec r|, |w(r)|) from w and |vec r|² (derivative 0, not NaN, at |vec r| = 0)."""
    positive = s2 > 0
    s = jnp.where(positive, jnp.sqrt(jnp.where(positive, s2, 1.0)), 0.0)
    return 2.0 * jnp.arctan2(s, jnp.abs(w))


def _angle_between(p: Array, q: Array) -> Array:
    """Geodesic angle in [0, π] between unit quaternions (sign-invariant, accurate for tiny angles):
    the norm of `to_rotvec(p* ⊗ q)` without forming the vector (it is taken every step with
    `statistics=True`)."""
    return _angle_of(*_relative_parts(p, q))


# ----------------------------------------------------------------------------------------------------
# Sharding helpers


def body_sharding(devices: Sequence[jax.Device] | None = None) -> NamedSharding:
    """The sharding `simulate_ensemble` uses: bodies (axis 0) split over a one-axis device mesh.

    **Arguments:**

    - `devices`: the devices to use, a sequence of distinct `jax.Device`s; default all of them
      (`jax.devices()`, every host's under `jax.distributed`).

    **Returns:** `NamedSharding(Mesh(devices, ("bodies",)), PartitionSpec("bodies"))`. Its `.mesh`
    shows the device layout.

    **Errors:** a `ValueError` when `devices` is not a non-empty sequence of distinct `jax.Device`s.
    """
    if devices is None:
        devices = jax.devices()
    elif isinstance(devices, (str, bytes)) or not isinstance(devices, Iterable):
        raise ValueError(
            "`devices` must be a sequence of jax.Device (e.g. `jax.devices()[:2]`); "
            f"got {type(devices).__name__}."
        )
    devices = list(devices)
    if not devices:
        raise ValueError("`devices` must name at least one device; got an empty list.")
    for device in devices:
        if not isinstance(device, jax.Device):
            raise ValueError(
                "`devices` must be a sequence of jax.Device (e.g. `jax.devices()[:2]`); got an "
                f"element {device!r} of type {type(device).__name__}."
            )
    if len(set(devices)) != len(devices):
        raise ValueError(f"`devices` must not name a device twice; got {devices}.")
    mesh = Mesh(np.asarray(devices, dtype=object), (_BODY_AXIS,))
    return NamedSharding(mesh, PartitionSpec(_BODY_AXIS))


def _time_major(sharding: NamedSharding) -> NamedSharding:
    return NamedSharding(sharding.mesh, PartitionSpec(None, _BODY_AXIS))


@partial(jax.jit, static_argnames=("padded", "sharding", "axis"))
def _pad_and_shard(
    x: Array, fill: Array, *, padded: int, sharding: NamedSharding, axis: int = 0
) -> Array:
    """Append copies of `fill` along `axis` up to `padded` rows, laid out with `sharding`."""
    extra = padded - x.shape[axis]
    if extra:
        shape = x.shape[:axis] + (extra,) + x.shape[axis + 1 :]
        x = jnp.concatenate([x, jnp.broadcast_to(fill, shape).astype(x.dtype)], axis=axis)
    return jax.lax.with_sharding_constraint(x, sharding)


@partial(jax.jit, static_argnames="total")
def _start_kept(parts: tuple[Array, ...], total: int) -> tuple[Array, ...]:
    """The in-memory saved states: the first chunk's, followed by room for the rest (time-major)."""
    return tuple(jnp.pad(x, ((0, total - x.shape[0]),) + ((0, 0),) * (x.ndim - 1)) for x in parts)


@partial(jax.jit, donate_argnums=0)
def _keep_at(kept: tuple[Array, ...], parts: tuple[Array, ...], offset: Array) -> tuple[Array, ...]:
    """Write a chunk's saved states into the kept ones at `offset`, in place (the kept are donated):
    the run holds its saved states once, not twice as joining the chunks at the end would."""
    return tuple(
        jax.lax.dynamic_update_slice_in_dim(k, x, offset, axis=0)
        for k, x in zip(kept, parts, strict=True)
    )


def _refuse_traced(x, path: str) -> None:
    """States traced though no input was: an `omega` or `torque` closing over a traced value."""
    if is_tracer(x):
        raise ValueError(
            "`path`: the run's states are traced (an `omega` or `torque` closes over a value traced "
            f"by jax.jit, jax.vmap or a derivative), so they cannot be written; {path!r} holds an "
            "incomplete run. Pass path=None and keep the result in memory."
        )


def _to_host(x: Array) -> np.ndarray:
    """Fetch a (possibly multi-host) sharded array to the host as a NumPy array."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)


# ----------------------------------------------------------------------------------------------------
# One chunk of steps (compiled; no host work inside)


def _update_statistics(stats, q_start, q, q_next):
    """Per-step statistics: Σ step angles, and the farthest rotation r = q_start* ⊗ q so far.

    The sum is Kahan-compensated (`_compensated_add`): a plain float32 sum of 10⁶ steps of ~3e-3 rad
    rounded each addition to the total's spacing, 1.35e-2 relative low after 3,000 rad (a review).

    The farthest rotation is kept as (|vec r|², |w(r)|), so a step costs one relative rotation and
    two selects; its angle is taken once, at the end (`_farthest_angle`). Rotations are compared by
    tan²(θ/2) = |vec r|²/w², cross-multiplied, which resolves angles near π as well as near 0
    (sin²(θ/2) = |vec r|² alone rounds to the same value for π − 1e-8 and π − 1e-12, and kept the
    first: a review). The step angle needs one atan2 per step (the dominant cost of statistics).
    """
    total, total_c, farthest_s2, farthest_w = stats
    w, s2 = _relative_parts(q_start, q_next)
    further = s2 * (farthest_w * farthest_w) > farthest_s2 * (w * w)
    farthest_s2 = jnp.where(further, s2, farthest_s2)
    farthest_w = jnp.where(further, jnp.abs(w), farthest_w)
    total, total_c = _compensated_add(total, _angle_between(q, q_next), total_c)
    return total, total_c, farthest_s2, farthest_w


def _farthest_angle(farthest_s2: Array, farthest_w: Array) -> Array:
    return _angle_of(farthest_w, farthest_s2)


def _omega_source(
    omega_fn: Callable, t0: Array, dt: Array, eps: float | None = None
) -> tuple[Callable, Array]:
    """The callable ω as the steps call it, `source(t, q)`, and the time `t0` of step 0 it expects.

    As in `integrate`, a `Sampled` ω is looked up by the time since its first sample (the steps'
    times are then `shift + k·dt`, shift = t0 − its t0), so float32 runs at large t pick the samples
    exactly; a step going backwards holds the sample of the interval it crosses.
    """
    if isinstance(omega_fn, Sampled):
        shift = t0 - jnp.asarray(omega_fn.t0).astype(t0.dtype)
        return omega_fn._relative(shift, dt < 0, eps), shift
    return omega_fn, t0


def _renormalized(qc):
    """q/|q|, and the Kahan compensation (if any) reset, at a renormalisation step."""
    q, c = qc
    return q / safe_norm(q, keepdims=True), None if c is None else jnp.zeros_like(c)


def _kinematic_step_fn(config, omega_fn, omega, dt, t0, q_start, offset):
    """The per-step update `(k, carry) -> carry` of a kinematic ensemble at global step `offset + k`.

    It is `integrate`'s step (the same `lie_step`, float32 Kahan-compensated increment form and
    renormalisation every `renormalize_every` global steps), with the compensation in the carry, so a
    run cut into chunks is bit-for-bit the run in one piece. `omega_fn` is the callable ω (or `None`
    for the constant `omega`); its output is broadcast to the `(bodies, 3)` of the state.
    """
    method, frame = config["method"], config["frame"]
    renormalize_every = config["renormalize_every"]
    if omega_fn is None:
        source = lambda t, q: omega  # noqa: E731
    else:
        source, t0 = _omega_source(omega_fn, t0, dt, config["time_eps"])

    def field(t, q, x):
        return jnp.broadcast_to(source(t, q), q.shape[:-1] + (3,)), None

    # A constant ω's Lie–Euler step is the same rotation every step: made once per chunk, outside
    # the loop, with the arithmetic of `lie_step` / `_compensated_step` (ω is per body, as q).
    hoisted = None
    if omega_fn is None and method == "euler":
        phi = jnp.asarray(dt).astype(omega.dtype) * omega
        hoisted = _rotation_minus_one(phi) if config["compensated"] else from_rotvec(phi)

    def step_fn(k, carry):
        q, c, stats = carry
        index = offset + k
        t = t0 + index.astype(t0.dtype) * dt
        if hoisted is not None and config["compensated"]:
            q_next, c = _compensated_add(q, _act(q, hoisted, frame), c)
        elif hoisted is not None:
            q_next = _act(q, hoisted, frame)
        elif config["compensated"]:
            q_next, c = _compensated_step(method, field, t, q, c, dt, frame)
        else:
            q_next, _ = lie_step(method, field, t, q, None, dt, frame=frame)
        if renormalize_every is not None:
            # A conditional, not a select: the norm is taken only when due (a select computed it,
            # and a division, every step: 2.3x (float64) and 3.6x (float32) the cost of a step).
            due = (index + 1) % renormalize_every == 0
            q_next, c = jax.lax.cond(due, _renormalized, lambda qc: qc, (q_next, c))
        if stats is not None:
            stats = _update_statistics(stats, q_start, q, q_next)
        return q_next, c, stats

    return step_fn


def _dynamic_step_fn(config, torque, dt, t0, q_start, offset):
    """The per-step update of a rigid-body ensemble (state in the body frame): `simulate_rigid_body`'s."""
    if torque is not None and config["frame"] == "world":
        user_torque = torque

        def torque(t, q, omega_body):
            tau_world = user_torque(t, q, rotate_unchecked(omega_body, q))
            return rotate_unchecked(tau_world, conjugate(q))

    def step_fn(k, carry):
        q, omega_body, inertia, c, stats = carry
        index = offset + k
        t = t0 + index.astype(t0.dtype) * dt
        # `simulate_rigid_body`'s step, with its float32 compensation and renormalisation carried
        # over the global step index (the compensation is in the carry).
        field = _rigid_body_field(inertia, torque, "body")
        q_next, omega_next, c = body_step(
            config["method"], field, t, q, omega_body, c, dt, index, config["renormalize_every"]
        )
        if stats is not None:
            stats = _update_statistics(stats, q_start, q, q_next)
        return q_next, omega_next, inertia, c, stats

    return step_fn


_CHUNK_STATIC = ("n_blocks", "block", "tail", "config")


def _run_chunk_steps(
    state, stats, q_start, dt, t0, start, params, *, n_blocks, block, tail, config, callables=None
):
    """Steps `start … start + n_blocks·block + tail` of the ensemble; saves the state after each block.

    Step k is at time `t0 + k·dt` with the integer global step index k, and everything a step needs is
    in the carry, so the result does not depend on how the run is cut into chunks. `params` holds the
    arrays of the callables ω and torque (dynamic: new values do not recompile), `config` their
    `static_key`s (`_split_callable`); or `callables` holds both whole (ω, torque), closed over by a
    program compiled for one call (callables that are not `reusable_callable`).
    """
    config = dict(config)
    dynamic = config["dynamic"]
    sharding = config["sharding"]
    if callables is not None:
        omega_fn, torque = callables
    else:
        omega_fn, torque = (
            _join_callable(arrays, static)
            for arrays, static in zip(params, (config["omega_fn"], config["torque"]), strict=True)
        )

    def constrain(tree):
        return jax.tree_util.tree_map(lambda x: jax.lax.with_sharding_constraint(x, sharding), tree)

    def advance(state, stats, offset, n):
        if dynamic:
            q, omega_body, inertia, c = state
            step_fn = _dynamic_step_fn(config, torque, dt, t0, q_start, offset)
            carry = (q, omega_body, inertia, c, stats)
        else:
            q, c, omega = state
            step_fn = _kinematic_step_fn(config, omega_fn, omega, dt, t0, q_start, offset)
            carry = (q, c, stats)
        carry, _ = scan_steps(
            step_fn, carry, n, save="final", checkpoint=False, unroll=config["unroll"]
        )
        state = carry[:-1] + ((omega,) if not dynamic else ())
        return constrain(state), constrain(carry[-1])

    def block_fn(carry, b):
        state, stats = advance(*carry, start + b * block, block)
        if dynamic:
            omega_out = state[1] if config["frame"] == "body" else _to_world(state[1], state[0])
            saved = (state[0], omega_out)
        else:
            saved = (state[0],)
        return (state, stats), saved if config["save"] else None

    saved = None
    if n_blocks:
        (state, stats), saved = jax.lax.scan(
            block_fn, (state, stats), jnp.arange(n_blocks, dtype=start.dtype)
        )
    if tail:
        state, stats = advance(state, stats, start + n_blocks * block, tail)
    return state, stats, saved


_run_chunk = jax.jit(_run_chunk_steps, static_argnames=_CHUNK_STATIC)


# ----------------------------------------------------------------------------------------------------
# Streaming saved states to disk


class _StateWriter:
    """Writes saved states to a directory: one `.npy` file per chunk plus a JSON index.

    Every file is written to a temporary name and renamed into place, and `index.json` is rewritten the
    same way after each chunk, so at any moment the directory holds a readable run with all completed
    chunks (an interrupted run included).
    """

    def __init__(self, path: str | os.PathLike, metadata: dict[str, Any], needed: int = 0):
        """`needed`: the bytes the run's data files will take; a run that cannot fit on the file
        system (counting the space a previous run in `path` frees) is a `ValueError` before anything
        is touched, instead of writing until the disk is full."""
        self.path = os.fspath(path)
        index_path = os.path.join(self.path, "index.json")
        if os.path.exists(self.path):
            if not os.path.isdir(self.path):
                raise ValueError(f"`path` {self.path!r} exists and is not a directory.")
            entries = set(os.listdir(self.path))
            if entries - {"index.json.tmp"} and "index.json" not in entries:
                raise ValueError(
                    f"`path` {self.path!r} is a non-empty directory that is not a jaxquat ensemble; "
                    "refusing to write into it."
                )
            previous = self._previous_files(index_path) if "index.json" in entries else []
            self._check_space(needed, previous)
            # Only the temporary of a first index: a run killed (SIGKILL) while writing it.
            if entries == {"index.json.tmp"}:
                os.remove(os.path.join(self.path, "index.json.tmp"))
            for name in previous:
                os.remove(name)
        else:
            self._check_space(needed, [])
            try:
                os.makedirs(self.path)
            except OSError as e:  # under a file, a dangling symbolic link, no permission, ...
                raise ValueError(
                    f"`path` {self.path!r} cannot be created as a directory "
                    f"({type(e).__name__}: {e.strerror or e})."
                ) from None
        self.index = dict(
            metadata,
            format=_FORMAT,
            version=_FORMAT_VERSION,
            complete=False,
            steps_done=0,
            records=[],
            final={},
        )
        self._write_index()

    def _check_space(self, needed: int, previous: list[str]) -> None:
        """A `ValueError` if `needed` bytes exceed the free space of the file system holding `path`
        (its nearest existing directory) plus the size of the `previous` run's files."""
        directory = os.path.abspath(self.path)
        while not os.path.isdir(directory) and os.path.dirname(directory) != directory:
            directory = os.path.dirname(directory)
        try:
            free = shutil.disk_usage(directory).free
            free += sum(os.path.getsize(name) for name in previous)
        except OSError:  # (the writes will say what is wrong)
            return
        if needed > free:
            raise ValueError(
                f"`path` {self.path!r}: the saved states need {needed / 1e9:.3g} GB and the file "
                f"system holding it has {free / 1e9:.3g} GB free; save less often (`save_every`), "
                "fewer bodies, or elsewhere."
            )

    def _previous_files(self, index_path) -> list[str]:
        """The data files named by the index of a previous run in `path` (only plain `.npy` names
        inside it, that exist), to be removed. An index that is not JSON, not a jaxquat ensemble's,
        or whose `records` (a list of tables, each with a table of `files`) or `final` (a table) are
        malformed is a `ValueError` naming the file."""
        try:
            with open(index_path, encoding="utf-8-sig") as f:
                old = json.load(f)
        except (OSError, ValueError, RecursionError) as e:
            raise ValueError(
                f"`path` {self.path!r} holds an unreadable index.json ({type(e).__name__}: {e})."
            ) from e
        if not isinstance(old, dict) or old.get("format") != _FORMAT:
            raise ValueError(
                f"`path` {self.path!r} holds an index.json that is not a jaxquat ensemble."
            )
        records, final = old.get("records", []), old.get("final", {})
        if not isinstance(records, list) or not all(
            isinstance(r, dict) and isinstance(r.get("files", {}), dict) for r in records
        ):
            problem = f"records must be a list of {{steps, files}} tables, got {records!r}"
        elif not isinstance(final, dict):
            problem = f"final must be a table of files, got {final!r}"
        else:
            problem = None
        if problem is not None:
            raise ValueError(
                f"`path` {self.path!r} holds a malformed jaxquat ensemble index.json ({problem:.200}); "
                "refusing to write into it."
            )
        names = [n for r in records for n in r.get("files", {}).values()]
        names += list(final.values())
        files = [os.path.join(self.path, n) for n in dict.fromkeys(names) if _plain_npy_name(n)]
        return [name for name in files if os.path.isfile(name)]

    def _save(self, name: str, array: np.ndarray) -> None:
        _replace_atomically(os.path.join(self.path, name), "wb", lambda f: np.save(f, array))

    def _write_index(self) -> None:
        _replace_atomically(
            os.path.join(self.path, "index.json"), "w", lambda f: json.dump(self.index, f, indent=1)
        )

    def write_record(
        self, arrays: dict[str, np.ndarray], steps: list[int], steps_done: int
    ) -> None:
        number = len(self.index["records"])
        files = {}
        for key, array in arrays.items():
            files[key] = f"{key}_{number:06d}.npy"
            self._save(files[key], array)
        self.index["records"].append({"steps": steps, "files": files})
        self.index["steps_done"] = steps_done
        self._write_index()

    def progress(self, steps_done: int) -> None:
        self.index["steps_done"] = steps_done
        self._write_index()

    def finish(self, arrays: dict[str, np.ndarray]) -> None:
        for key, array in arrays.items():
            self.index["final"][key] = f"{key}.npy"
            self._save(f"{key}.npy", array)
        self.index["complete"] = True
        self._write_index()


def _replace_atomically(target: str, mode: str, write: Callable[[Any], None]) -> None:
    """Write `target` through a temporary file and rename it into place, so a reader never sees half
    a file; the temporary is removed if writing fails or is interrupted (Ctrl-C, a full disk)."""
    temporary = target + ".tmp"
    try:
        try:
            with open(temporary, mode) as f:
                write(f)
        except OSError as e:
            if e.errno is not None:
                raise
            # NumPy reports a short write as "40000 requested and 26592 written", with no file and
            # no error number: say which file, and the likely cause.
            raise OSError(errno.ENOSPC, f"{e} (is the disk full?)", target) from None
        os.replace(temporary, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(temporary)
        raise


def load_ensemble(path: str | os.PathLike) -> dict[str, Any]:
    """Read an ensemble written by `simulate_ensemble(..., path=...)` (complete or interrupted).

    **Arguments:**

    - `path`: the directory given as `path`.

    **Returns:** a dict with
    - `"states"`: saved orientations, time-major `(num_saved, *batch, 4)` (only completed chunks);
    - `"omegas"`: saved angular velocities `(num_saved, *batch, 3)` for rigid-body ensembles;
    - `"steps"` / `"times"`: the step indices and times of the saved states;
    - `"complete"`: whether the run finished; `"steps_done"`: steps completed;
    - after a complete run also `"final"`, `"final_omega"`, `"angle_from_start"` and, if computed,
      `"total_angle"` and `"max_angle_from_start"`;
    - `"finite"`: whether every array read is free of NaN and infinity (a run that overflowed, with
      too large a `dt` for instance, is written as it ended: check this before using the results);
    - `"metadata"`: the run's parameters (method, frame, dt, …).

    A directory that is not such a run, or one whose index or files are damaged or inconsistent
    (an index from another format version, a complete run lacking states or final arrays, saved
    times that overflow), is a `ValueError` naming the file and the problem. What is checked is the
    structure: the index's fields, each array's file, dtype and shape, and (reported in `"finite"`)
    its finiteness. The values themselves are not (a hand-edited `final.npy` of zeros or of non-unit
    quaternions loads as written), nor is the index's account of the run beyond its consistency
    (edited to `"dynamic": false`, a rigid-body run loads without its `"omegas"`).
    """
    path = _check_path(path)
    if not os.path.exists(path):
        raise ValueError(f"`path` {path!r} does not exist.")
    if not os.path.isdir(path):
        raise ValueError(f"`path` {path!r} is not a directory: not a jaxquat ensemble.")
    index_path = os.path.join(path, "index.json")
    if not os.path.isfile(index_path):
        raise ValueError(f"`path` {path!r} has no index.json: not a jaxquat ensemble.")
    try:
        return _read_ensemble(path, index_path)
    except _MalformedEnsemble as e:
        raise ValueError(f"`path` {path!r}: {e}") from None
    except (
        OSError,
        ValueError,
        KeyError,
        TypeError,
        IndexError,
        AttributeError,
        EOFError,
        OverflowError,
        RecursionError,
    ) as e:
        # A truncated or edited index or data file: one clear error, never a partial result.
        raise ValueError(
            f"`path` {path!r}: malformed jaxquat ensemble ({type(e).__name__}: {e})."
        ) from e


class _MalformedEnsemble(Exception):
    pass


def _without_repeated_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object as a dict, refusing a key given twice (`json` keeps the last one silently:
    `"dt": 0.01, "dt": 0.02` in an edited index doubled every saved time)."""
    counts = collections.Counter(key for key, _ in pairs)
    repeated = sorted(key for key, count in counts.items() if count > 1)
    if repeated:
        raise _MalformedEnsemble(f"index.json gives {', '.join(map(repr, repeated))} twice.")
    return dict(pairs)


def _index_int(
    index: dict, key: str, *, minimum: int = 0, steps: bool = False, optional: bool = False
) -> int | None:
    """An integer >= `minimum`; a step count (`steps`) at most 2**31 - 1, as the writer's counter."""
    value = index.get(key) if optional else index[key]
    if optional and value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise _MalformedEnsemble(
            f"index.json: {key} must be an integer >= {minimum}, got {value!r}."
        )
    if steps and value > _MAX_STEPS:
        raise _MalformedEnsemble(
            f"index.json: {key} must be at most 2**31 - 1 = {_MAX_STEPS}, got {value}."
        )
    return value


def _index_float(index: dict, key: str) -> float:
    value = index[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise _MalformedEnsemble(f"index.json: {key} must be a finite number, got {value!r}.")
    return float(value)


def _index_bool(index: dict, key: str) -> bool:
    value = index[key]
    if not isinstance(value, bool):
        raise _MalformedEnsemble(f"index.json: {key} must be true or false, got {value!r}.")
    return value


def _plain_npy_name(name) -> bool:
    """Whether `name` is a bare `.npy` file name (no directory part, nothing leading elsewhere)."""
    return (
        isinstance(name, str)
        and name.endswith(".npy")
        and name not in (".npy", "..npy")
        and os.path.basename(name) == name
        and not (os.path.altsep is not None and os.path.altsep in name)
        and not os.path.isabs(name)
        and "\0" not in name
    )


def _data_file(path: str, name, where: str) -> str:
    """The file `name` inside the ensemble directory; names that lead elsewhere are refused."""
    if not _plain_npy_name(name):
        raise _MalformedEnsemble(
            f"index.json: {where} names {name!r}, expected a plain .npy file name inside the "
            "ensemble directory."
        )
    return os.path.join(path, name)


def _load_array(path: str, name, where: str, label: str, shape: tuple, dtype) -> np.ndarray:
    """The array in the data file `name` (see `_data_file`), which must hold `dtype[shape]`; an
    unreadable or mismatched file is named (`label` says which, e.g. "record 0").

    The header is read first, so a file whose header claims a huge shape is refused before anything
    is allocated. bfloat16, which NumPy has no name for, is stored by `np.save` as 2-byte void records
    (`|V2`) and read back as bfloat16.
    """
    filename = _data_file(path, name, where)
    dtype = np.dtype(dtype)
    stored_as = np.dtype("V2") if dtype == jnp.bfloat16 else dtype
    try:
        with open(filename, "rb") as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                header = np.lib.format.read_array_header_1_0(f)
            elif version == (2, 0):
                header = np.lib.format.read_array_header_2_0(f)
            else:
                raise ValueError(f"unsupported .npy format version {version}")
            file_shape, _, file_dtype = header
            if tuple(file_shape) != tuple(shape) or file_dtype != stored_as:
                shown = dtype if file_dtype == stored_as else file_dtype
                raise _MalformedEnsemble(
                    f"{name} ({label}) holds {shown}{list(file_shape)}, the index says "
                    f"{dtype}{list(shape)}."
                )
            f.seek(0)
            array = np.load(f, allow_pickle=False)
            extra = os.fstat(f.fileno()).st_size - f.tell()
            if extra:  # (np.load stops at the end of the data and ignores the rest)
                raise _MalformedEnsemble(
                    f"malformed jaxquat ensemble: {name}, {where}, has {extra:,} bytes after its "
                    f"{dtype}{list(shape)} data."
                )
    except FileNotFoundError:
        raise _MalformedEnsemble(
            f"malformed jaxquat ensemble: {name}, {where}, is missing."
        ) from None
    # EOFError: an empty (zero-length) file. A damaged header NumPy cannot parse directly goes to
    # `tokenize` and `ast.literal_eval`: TokenError, SyntaxError, TypeError or RecursionError.
    except (OSError, ValueError, EOFError, TokenError, SyntaxError, TypeError, RecursionError) as e:
        raise _MalformedEnsemble(
            f"malformed jaxquat ensemble: {name}, {where}, is not a readable .npy file "
            f"({type(e).__name__}: {e})."
        ) from None
    except MemoryError:
        raise _MalformedEnsemble(
            f"{name}, {where}, holds {dtype}{list(shape)}: more than this machine can allocate."
        ) from None
    return array.view(dtype) if stored_as != dtype else array


# What the writer's `finish` always writes (`total_angle`, `max_angle_from_start` with statistics).
_FINAL_ALWAYS = ("final", "final_omega", "angle_from_start")


def _check_complete(
    steps: list[int], final: dict, steps_done: int, save_every: int | None, known: bool
) -> None:
    """A complete run has what its writer wrote: every saved state and the final arrays.

    With `save_every` the writer records the initial state and then each chunk's states, so a
    complete run holds steps 0, save_every, 2·save_every, … up to steps_done; without it, none.
    `known`: whether the index says `save_every` at all (every writer so far has).
    """
    missing = [key for key in _FINAL_ALWAYS if key not in final]
    if missing:
        raise _MalformedEnsemble(
            f"index.json: complete, but final lacks {', '.join(missing)} (the writer saves "
            "them when the run completes)."
        )
    if not known:
        return
    expected = list(range(0, steps_done + 1, save_every)) if save_every else []
    if len(steps) != len(expected):
        raise _MalformedEnsemble(
            f"index.json: complete, but its records hold {len(steps)} saved states where "
            f"save_every {save_every} and steps_done {steps_done} make {len(expected)}."
        )
    for step, due in zip(steps, expected, strict=True):
        if step != due:
            raise _MalformedEnsemble(
                f"index.json: complete, but saved step {step} is not step {due} (every "
                f"save_every {save_every} steps from 0)."
            )


def _read_ensemble(path: str, index_path: str) -> dict[str, Any]:
    try:
        # utf-8-sig: an index saved again by an editor that adds a byte-order mark still reads (as
        # the command line's CSV and TOML files do).
        with open(index_path, encoding="utf-8-sig") as f:
            index = json.load(f, object_pairs_hook=_without_repeated_keys)
    except RecursionError:  # the JSON decoder recurses once per level of nesting
        raise _MalformedEnsemble(
            "index.json is nested too deeply to be a jaxquat ensemble index."
        ) from None
    except ValueError as e:  # not JSON, or not UTF-8
        raise _MalformedEnsemble(
            f"index.json is not valid JSON ({type(e).__name__}: {e})."
        ) from None
    if not isinstance(index, dict) or index.get("format") != _FORMAT:
        raise _MalformedEnsemble(
            "index.json is not a jaxquat ensemble index (not a jaxquat ensemble)."
        )
    if isinstance(index.get("version"), bool) or index.get("version") != _FORMAT_VERSION:
        raise _MalformedEnsemble(
            f"index.json: format version {index.get('version')!r} is not one this jaxquat reads "
            f"(version {_FORMAT_VERSION})."
        )
    shape = index["batch_shape"]
    if not isinstance(shape, list) or any(
        isinstance(n, bool) or not isinstance(n, int) or n < 0 for n in shape
    ):
        raise _MalformedEnsemble(
            f"index.json: batch_shape must be a list of non-negative integers, got {shape!r}."
        )
    batch = tuple(shape)
    if index["dtype"] not in ("float16", "bfloat16", "float32", "float64"):
        raise _MalformedEnsemble(
            f"index.json: dtype must name a float dtype, got {index['dtype']!r}."
        )
    dtype = jnp.dtype(index["dtype"])
    # The run's account, where the index gives it, must agree with itself (an edited count or a
    # frame no run has loaded as written).
    if "num_bodies" in index and (
        isinstance(index["num_bodies"], bool) or index["num_bodies"] != math.prod(batch)
    ):
        raise _MalformedEnsemble(
            f"index.json: num_bodies {index['num_bodies']!r} is not the number of bodies of "
            f"batch_shape {shape} ({math.prod(batch)})."
        )
    for key, known in (("frame", ("world", "body")), ("method", METHODS)):
        if key in index and index[key] not in known:
            raise _MalformedEnsemble(
                f"index.json: {key} must be one of {', '.join(known)}; got {index[key]!r}."
            )
    dynamic = _index_bool(index, "dynamic") if "dynamic" in index else False
    complete = _index_bool(index, "complete")
    t0 = _index_float(index, "t0")
    dt = _index_float(index, "dt")
    num_steps = _index_int(index, "num_steps", steps=True) if "num_steps" in index else None
    steps_done = _index_int(index, "steps_done", steps=True)
    save_every = _index_int(index, "save_every", minimum=1, optional=True)
    if num_steps is not None and steps_done > num_steps:
        raise _MalformedEnsemble(
            f"index.json: steps_done {steps_done} exceeds num_steps {num_steps}."
        )
    if complete and num_steps is not None and steps_done != num_steps:
        raise _MalformedEnsemble(
            f"index.json: complete, but steps_done {steps_done} != num_steps {num_steps}."
        )
    records = index["records"]
    if not isinstance(records, list) or not all(isinstance(r, dict) for r in records):
        raise _MalformedEnsemble("index.json: records must be a list of {steps, files} tables.")
    for number, record in enumerate(records):  # a missing key is a KeyError, reported as such
        if not isinstance(record["steps"], list) or not isinstance(record["files"], dict):
            raise _MalformedEnsemble(
                f"index.json: record {number} must have a list of steps and a table of files."
            )
    steps = [s for r in records for s in r["steps"]]
    if any(isinstance(k, bool) or not isinstance(k, int) or k < 0 for k in steps):
        raise _MalformedEnsemble(
            f"index.json: saved steps must be non-negative integers, got {steps!r}."
        )
    if any(b <= a for a, b in zip(steps, steps[1:], strict=False)) or (
        steps and steps[-1] > steps_done
    ):
        raise _MalformedEnsemble(
            f"index.json: saved steps must increase and not exceed steps_done {steps_done}, "
            f"got {steps!r}."
        )
    final = index.get("final", {})
    if not isinstance(final, dict):
        raise _MalformedEnsemble(f"index.json: final must be a table of files, got {final!r}.")
    final_shapes = {
        "final": batch + (4,),
        "final_omega": batch + (3,),
        "angle_from_start": batch,
        "total_angle": batch,
        "max_angle_from_start": batch,
    }
    for key in final:
        if key not in final_shapes:
            raise _MalformedEnsemble(
                f"index.json: unknown final array {key!r} (known: {', '.join(final_shapes)})."
            )
    if complete:
        _check_complete(steps, final, steps_done, save_every, "save_every" in index)
    out: dict[str, Any] = {"steps": np.asarray(steps, dtype=np.int64)}
    with np.errstate(over="ignore", invalid="ignore"):
        out["times"] = t0 + dt * out["steps"].astype(np.float64)
    if not np.all(np.isfinite(out["times"])):
        first = int(np.argmin(np.isfinite(out["times"])))
        raise _MalformedEnsemble(
            f"index.json: the time t0 + k·dt of saved step k = {steps[first]} is not finite "
            f"(t0 {t0!r}, dt {dt!r})."
        )
    finite = True
    widths = {"states": 4, "omegas": 3} if dynamic else {"states": 4}
    for key, width in widths.items():
        parts = []
        for number, record in enumerate(records):
            name = record["files"][key]
            expected = (len(record["steps"]),) + batch + (width,)
            part = _load_array(
                path, name, f"record {number} ({key})", f"record {number}", expected, dtype
            )
            finite = finite and bool(np.isfinite(part).all())  # one chunk's temporary at a time
            parts.append(part)
        out[key] = (
            np.concatenate(parts, axis=0) if parts else np.zeros((0,) + batch + (width,), dtype)
        )
    for key, name in final.items():
        part = _load_array(path, name, f"final ({key})", key, final_shapes[key], dtype)
        finite = finite and bool(np.isfinite(part).all())
        out[key] = part
    out["complete"] = complete
    out["steps_done"] = steps_done
    out["finite"] = finite
    out["metadata"] = {k: v for k, v in index.items() if k not in ("records", "final")}
    return out


# ----------------------------------------------------------------------------------------------------
# The public entry point


# The largest step count: step indices are int32 on the device.
_MAX_STEPS = 2**31 - 1


def _check_positive_int(value, name: str, *, allow_zero: bool = False) -> int:
    """An integer of any kind (Python, NumPy, a concrete JAX scalar, as `integrate` takes), not a
    bool, a float or a traced value."""
    count = integer_value(value)
    if count is None:
        raise ValueError(f"`{name}` must be an integer; got {value!r}.")
    value = count
    low = 0 if allow_zero else 1
    if value < low:
        raise ValueError(f"`{name}` must be {'>= 0' if allow_zero else '>= 1'}; got {value}.")
    return int(value)


def _check_real_scalar(value, name: str) -> None:
    """A finite real scalar (Python, NumPy or JAX number; not a bool or a string). A traced one
    (under jax.jit or a derivative) is checked for its shape and dtype only (a float or an integer,
    as a concrete one may be)."""
    if is_tracer(value):
        real = jnp.issubdtype(value.dtype, jnp.floating) or jnp.issubdtype(value.dtype, jnp.integer)
        if value.ndim != 0 or not real:
            raise ValueError(
                f"`{name}` must be a real scalar; got a traced {value.dtype} of shape {value.shape}."
            )
        return
    try:
        array = np.asarray(value)
    except Exception:  # noqa: BLE001 (an exotic object: refused below)
        array = None
    if (
        array is None
        or isinstance(value, (bool, np.bool_))
        or array.ndim != 0
        or not (np.issubdtype(array.dtype, np.integer) or np.issubdtype(array.dtype, np.floating))
    ):
        raise ValueError(f"`{name}` must be a real scalar (a number); got {value!r}.")
    if not np.isfinite(array):
        raise ValueError(f"`{name}` must be finite; got {value!r}.")


def _check_inertia(inertia: ArrayLike) -> tuple[Array, tuple[int, ...]]:
    """Principal moments `(..., 3)` or matrices `(..., 3, 3)`, finite and positive definite."""
    inertia = as_float_array(inertia, "inertia")
    if inertia.ndim >= 2 and inertia.shape[-2:] == (3, 3):
        batch = inertia.shape[:-2]
    elif inertia.ndim >= 1 and inertia.shape[-1] == 3:
        batch = inertia.shape[:-1]
    else:
        raise ValueError(
            "`inertia` must be principal moments (..., 3) or matrices (..., 3, 3); "
            f"got shape {tuple(inertia.shape)}."
        )
    # Finiteness, symmetry and positivity (when concrete), with `simulate_rigid_body`'s check.
    return _check_rigid_inertia(inertia), batch


def _check_omega_fn(omega_fn: Callable, method: str, t0: Array, dt: Array, q: Array) -> None:
    """Check a callable ω as `integrate` does, on the ensemble's state `q` (bodies, 4): it must return
    `(..., 3)` broadcasting to (bodies, 3), and not depend on q for a Magnus method."""
    source, t0 = _omega_source(omega_fn, t0, dt)

    def omega(t, q):
        return as_float_array(source(t, q), "omega(t, q)")

    shape = tuple(getattr(jax.eval_shape(omega, t0, q), "shape", ()))
    if len(shape) == 0 or shape[-1] != 3:
        raise ValueError(f"`omega(t, q)` must return shape (..., 3); got shape {shape}.")
    bodies = q.shape[:-1]
    try:
        fits = np.broadcast_shapes(shape[:-1], bodies) == bodies
    except ValueError:
        fits = False
    if not fits:
        raise ValueError(
            f"`omega(t, q)` is called on all bodies at once, flattened and padded to a multiple of "
            f"the device count (q of shape {tuple(q.shape)}), and must act element-wise: return "
            f"shape (..., 3) broadcasting to {bodies + (3,)}; got shape {shape} (per-body samples: "
            "use `jaxquat.sampled`)."
        )
    _check_magnus_omega(omega, method, t0, q)


def _split_callable(fn: Callable | None, sharding: NamedSharding) -> tuple[Any, Any]:
    """A `reusable_callable` split into its arrays, placed with `sharding` unless already laid out on
    its mesh (a list with None for the other leaves: dynamic arguments of the compiled chunk), and
    its hashable `static_key` (a static argument); `_join_callable` puts them back together."""
    if fn is None:
        return None, None

    def place(x):
        current = getattr(x, "sharding", None)
        if isinstance(current, NamedSharding) and current.mesh == sharding.mesh:
            return x
        return jax.device_put(x, sharding)

    leaves = jax.tree_util.tree_leaves(fn)
    return [place(x) if eqx.is_array(x) else None for x in leaves], static_key(fn)


def _join_callable(arrays, static):
    """The callable `_split_callable` split."""
    if static is None:
        return None
    structure, rest = static
    leaves = [x if x is not None else r for x, r in zip(arrays, rest, strict=True)]
    return jax.tree_util.tree_unflatten(structure, leaves)


def _check_path(path) -> str:
    """`path` as a `str` (a bytes path decoded); a `ValueError` unless it is a non-empty str or
    os.PathLike."""
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(
            f"`path` must be a directory name (str or os.PathLike); got {type(path).__name__}."
        )
    path = os.fspath(path)
    if not isinstance(path, str):  # a bytes path
        path = os.fsdecode(path)
    if not path:
        raise ValueError("`path` must name a directory; got ''.")
    return path


def _default_chunk(num_steps: int, num_bodies: int, save_every: int | None) -> int:
    body_steps = _BODY_STEPS_PER_CHUNK
    if save_every:
        body_steps = min(body_steps, _SAVED_STATES_PER_CHUNK * save_every)
    chunk = max(1, body_steps // max(num_bodies, 1))
    chunk = min(chunk, max(num_steps, 1))
    # Equal chunks share one compilation: use the smallest chunk length giving the same count.
    count = -(-max(num_steps, 1) // chunk)
    chunk = -(-max(num_steps, 1) // count)
    if save_every:
        chunk = save_every * max(1, round(chunk / save_every))
    return chunk


def _auto_typed(x: Any) -> Any:
    """`x` with its sharding's explicit axes made automatic (the same devices and layout, no copy);
    anything else unchanged."""
    sharding = getattr(x, "sharding", None)
    if not (isinstance(x, jax.Array) and isinstance(sharding, NamedSharding)) or is_tracer(x):
        return x
    mesh = sharding.mesh
    if not mesh.explicit_axes:
        return x
    auto = Mesh(
        mesh.devices,
        mesh.axis_names,
        axis_types=(jax.sharding.AxisType.Auto,) * len(mesh.axis_names),
    )
    return jax.device_put(x, NamedSharding(auto, sharding.spec))


def _on_devices(x: Any, mesh: Mesh | None) -> Any:
    """`x`, an array committed to devices other than `mesh`'s (put on one device with
    `jax.device_put`, or laid out over other devices), copied onto `mesh` replicated: the compiled
    calls lay the bodies out with sharding constraints on `mesh`, and refuse arguments committed
    elsewhere ("incompatible devices"). Anything else unchanged."""
    if mesh is None or not isinstance(x, jax.Array) or is_tracer(x) or not x.committed:
        return x
    if x.sharding.device_set == set(mesh.devices.flat):
        return x
    return jax.device_put(x, NamedSharding(mesh, PartitionSpec()))


def _batch_layout(batch: tuple[int, ...], mesh: Mesh) -> tuple[Mesh, tuple] | None:
    """The bodies' mesh reshaped over the batch axes, with the partition spec of those axes, such
    that each device keeps exactly the bodies it holds in the flattened layout: contiguous blocks of
    the row-major order, which split the leading axes whole and then one axis evenly (on 4 devices
    (2, 4) is 2 × 2, (4, 2) is 4 × 1, (3, 4) has none). `None` if there is no such reshape.

    Without it the unflattened results of a multi-axis batch whose first axis the device count does
    not divide were laid out replicated: 4× the memory on 4 devices."""
    factors, remaining = [], mesh.size
    for size in batch:
        if size % remaining == 0:  # this axis takes what is left of the devices: the last split
            factors.append(remaining)
            remaining = 1
        elif remaining % size == 0:  # split whole, one index per device group
            factors.append(size)
            remaining //= size
        else:
            return None
    split = [i for i, f in enumerate(factors) if f > 1]
    if len(split) <= 1:
        spec = tuple("bodies" if i in split else None for i in range(len(batch)))
        return mesh, spec
    names = tuple("bodies" if k == 0 else f"bodies_{k}" for k in range(len(split)))
    devices = mesh.devices.reshape(tuple(factors[i] for i in split))
    spec = tuple(names[split.index(i)] if i in split else None for i in range(len(batch)))
    return Mesh(devices, names), spec


def _unpad_body(x, num_bodies, batch, sharding, time_major):
    x = x[:, :num_bodies] if time_major else x[:num_bodies]
    lead = x.shape[:1] if time_major else ()
    x = x.reshape(lead + batch + x.shape[len(lead) + 1 :])
    return x if sharding is None else jax.lax.with_sharding_constraint(x, sharding)


_UNPAD_STATIC = ("num_bodies", "batch", "sharding", "time_major")
_unpad_jit = jax.jit(_unpad_body, static_argnames=_UNPAD_STATIC)
# The saved states are the ensemble's own buffer, as large as everything else together: donated,
# the reshape reuses it (without, the run's peak memory held them twice: 2.2x their size, not 1.35x).
_unpad_donated = jax.jit(_unpad_body, static_argnames=_UNPAD_STATIC, donate_argnums=0)


def _unpadded(x, num_bodies, batch, layout, *, time_major):
    """The bodies of `x` (axis 0, or 1 if `time_major`: the saved states, whose buffer is donated)
    without the padding, in the batch shape, laid out over `layout` (see `_batch_layout`) when there
    is one."""
    sharding = None
    if layout is not None:
        mesh, spec = layout
        lead = (None,) if time_major else ()
        trailing = (None,) * (x.ndim - len(lead) - 1)
        sharding = NamedSharding(mesh, PartitionSpec(*lead, *spec, *trailing))
    # (Padding dropped, the result is smaller: nothing to reuse, and JAX warns of an unused donation.)
    unpad = _unpad_donated if time_major and x.shape[1] == num_bodies else _unpad_jit
    return unpad(x, num_bodies, batch, sharding, time_major)


def _on_own_mesh(simulate: Callable) -> Callable:
    """`simulate_ensemble` on its own mesh, whatever mesh the caller has set: it lays the bodies out
    itself (`body_sharding`), by sharding constraints that a mesh of explicit axes set with
    `jax.set_mesh` (the default of `jax.make_mesh`) turns into assertions, and it takes arrays
    sharded with explicit axes as their data (retyped with automatic axes, not copied), and arrays
    committed to other devices than its own (copied onto them)."""

    @wraps(simulate)
    def run(q0, omega, *args, inertia=None, torque=None, devices=None, t0=0.0, **kwargs):
        try:
            mesh = body_sharding(devices).mesh
        except ValueError:
            mesh = None  # (bad `devices`: refused with the other arguments' checks)

        def retyped(tree):
            return jax.tree_util.tree_map(lambda x: _on_devices(_auto_typed(x), mesh), tree)

        q0, omega, inertia, torque, t0 = (retyped(x) for x in (q0, omega, inertia, torque, t0))
        args = tuple(retyped(x) for x in args)  # dt (and num_steps)
        call = partial(
            simulate, q0, omega, *args, inertia=inertia, torque=torque, devices=devices, t0=t0
        )
        if not explicit_mesh():
            return call(**kwargs)
        try:
            context = jax.set_mesh(body_sharding(devices).mesh)
        except ValueError:  # JAX sets no concrete mesh while tracing
            raise ValueError(
                "simulate_ensemble under jax.jit, jax.vmap or a derivative cannot run inside "
                "`jax.set_mesh` with a mesh of explicit axes (jax.make_mesh's default): it lays "
                "the bodies out on a mesh of its own. Call it outside the transformation, or "
                "outside `jax.set_mesh`, or make the mesh with automatic axes "
                "(`axis_types=(jax.sharding.AxisType.Auto,)`)."
            ) from None
        with context:
            return call(**kwargs)

    return run


@_on_own_mesh
def simulate_ensemble(
    q0: ArrayLike,
    omega: ArrayLike | Callable,
    dt: float,
    num_steps: int,
    *,
    inertia: ArrayLike | None = None,
    torque: Callable | None = None,
    frame: str | None = None,
    method: str | None = None,
    t0: float = 0.0,
    save_every: int | None = None,
    statistics: bool = False,
    chunk_size: int | None = None,
    path: str | os.PathLike | None = None,
    devices: Sequence[jax.Device] | None = None,
    progress: bool | Callable[[int, int], None] = False,
    metadata: dict[str, Any] | None = None,
) -> EnsembleResult:
    """Simulate many bodies at once, sharded over all devices, in chunks of time.

    Two kinds of ensemble:

    - **kinematic** (`inertia=None`): each body turns with a given angular velocity, advanced by
      `jaxquat.integrate` with `method` (default `"euler"`, exact for constant ω) in `frame`
      (default `"world"`). `omega` is a per-body constant `(..., 3)` or a callable `omega(t, q)`
      acting element-wise on a `(bodies, 4)` batch.
    - **rigid bodies** (`inertia` given): torque-free (or `torque(t, q, ω)`) rigid bodies advanced by
      `jaxquat.simulate_rigid_body` with `method` (default `"cf4"`); `omega` is the initial angular
      velocity in `frame` (default `"body"`).

    The body axis (all leading axes, flattened) is padded to a multiple of the device count and
    sharded over `devices` (default: all, `jax.devices()`); the padding is dropped from the results.
    Time runs in chunks of `chunk_size` steps: each chunk is one compiled call, and between chunks the
    host reports progress and writes saved states to `path`. Peak memory is about
    bodies × (state + chunk_size / save_every saved states) — independent of `num_steps` when streaming.

    **Arguments:**

    - `q0`: initial orientations `(..., 4)` (unit).
    - `omega`: angular velocities `(..., 3)` in rad/s (leading axes broadcast with `q0`), or for a
      kinematic ensemble a callable `omega(t, q) -> (..., 3)` (a function or an `equinox.Module`),
      called on all bodies at once, flattened and padded, `q` of shape `(padded bodies, 4)`: it must
      act element-wise (return `(3,)` or `(padded bodies, 3)`); or `jaxquat.sampled(omegas, dt)`
      with samples `(T, ..., 3)` whose leading axes broadcast with `q0` (laid out over the bodies).
      The arrays of an `equinox.Module` ω or torque are arguments of the compiled chunks,
      replicated over the devices: new values (e.g. trained parameters) do not recompile. Any other
      callable (a function, a bound method, a `functools.partial`, or a Module holding NumPy values)
      may read state that changes between calls: the chunks are then compiled at each call (once
      per chunk length), as in `simulate_rigid_body`.
    - `dt`: the time step (a scalar). `num_steps`: the number of steps, 0 … 2³¹ − 1.
    - `inertia`: `None` (kinematic), or principal moments `(3,)` / matrices `(3, 3)`, shared or per
      body `(..., 3)` / `(..., 3, 3)`. A trailing `(3, 3)` is always a matrix: for exactly three
      bodies with their own principal moments `m` `(3, 3)`, pass `jax.vmap(jnp.diag)(m)`.
    - `torque`: optional `torque(t, q, omega)` for rigid bodies (see `simulate_rigid_body`).
    - `frame`, `method`: as for `integrate` / `simulate_rigid_body`.
    - `t0`: the initial time; step k is at `t0 + k·dt`.
    - `save_every`: save the state every this many steps (including the initial state); `None` saves
      only the final state.
    - `statistics`: also accumulate per-body `total_angle` and `max_angle_from_start` on the device,
      at the resolution of single steps.
    - `chunk_size`: steps per chunk (rounded to a multiple of `save_every`); default about
      2²⁶ body-steps and at most 2²⁴ saved states per chunk.
    - `path`: a directory to stream the saved states into (one `.npy` file per chunk and an
      `index.json`; read it back with `jaxquat.load_ensemble`). The saved states are then not kept in
      memory. The final state and statistics are written when the run completes. Only outside JAX
      transformations: under `jax.jit`, `jax.vmap` or a derivative (a traced input, or any call
      inside `jit`) `path` is a `ValueError`, raised before the run already in `path` is touched.
      So is a run whose files cannot fit in the free space of the file system (counting what the
      run it replaces frees), instead of writing until the disk is full.
    - `devices`: the devices to shard over. The bodies are laid out on a mesh of their own over
      them, whatever mesh `jax.set_mesh` has set; under `jax.jit`, `jax.vmap` or a derivative, where
      JAX sets no concrete mesh, the set mesh's axes must be automatic (explicit axes, the default of
      `jax.make_mesh`, are a `ValueError` saying so).
    - `progress`: `False` (default), `True` for a tqdm progress bar on stderr, or a callable
      `progress(steps_done, num_steps)` called between chunks (raising from it, e.g.
      `KeyboardInterrupt`, stops the run and leaves `path` readable with the completed chunks).
    - `metadata`: a JSON-serialisable dict recorded in `path`'s `index.json` as `"run"` (e.g. what
      the initial state was drawn from, to reproduce the run); `load_ensemble(path)["metadata"]["run"]`.

    **Returns:** an `EnsembleResult`.

    **Errors:** a `ValueError` naming the argument for a bad `q0`, `omega`, `dt`, `t0`, `num_steps`,
    `inertia`, `torque`, `frame`, `method`, `save_every`, `chunk_size`, `statistics`, `progress`,
    `metadata` (not a JSON-serialisable dict), `path` (not a str or os.PathLike; a file; a
    non-empty directory that is not a jaxquat ensemble, or one whose index.json is unreadable or
    malformed; a run whose `dt` or `t0` is traced) or `devices` (not a non-empty sequence of
    distinct `jax.Device`s); for an ensemble with no bodies (a batch shape with a 0); for an
    `omega(t, q)` of the wrong shape; and, as in `integrate`, for a q-dependent `omega` with a
    Magnus method and for an `omega(t, q)` or `torque` that reads t when its step times t0 + k·dt
    need not increase (the time dtype's spacing exceeds half a step).

    **Example:**
    ```python
    key_q, key_w = jax.random.split(jax.random.key(0))
    q0 = jaxquat.random(key_q, (100_000,), jnp.float32)
    omega = jax.random.normal(key_w, (100_000, 3), jnp.float32)
    result = jaxquat.simulate_ensemble(q0, omega, 1e-2, 1_000, save_every=100)
    result.saved.shape  # (11, 100000, 4)
    ```
    """
    started = time.perf_counter()
    dynamic = inertia is not None
    frame = check_frame(("body" if dynamic else "world") if frame is None else frame)
    num_steps = _check_positive_int(num_steps, "num_steps", allow_zero=True)
    if num_steps > _MAX_STEPS:
        # Step indices are int32 on the device (t = t0 + k·dt is formed from them).
        raise ValueError(f"`num_steps` must be at most 2**31 - 1 = {_MAX_STEPS}; got {num_steps}.")
    if save_every is not None:
        save_every = _check_positive_int(save_every, "save_every")
    if chunk_size is not None:
        chunk_size = _check_positive_int(chunk_size, "chunk_size")
    if not isinstance(statistics, bool):
        raise ValueError(f"`statistics` must be True or False; got {statistics!r}.")
    if not (isinstance(progress, bool) or callable(progress)):
        raise ValueError(f"`progress` must be a bool or a callable; got {progress!r}.")
    if metadata is not None:
        try:
            if not isinstance(metadata, dict):
                raise TypeError(type(metadata).__name__)
            metadata = json.loads(json.dumps(metadata, allow_nan=False))
        except (TypeError, ValueError, RecursionError) as e:
            raise ValueError(
                f"`metadata` must be a JSON-serialisable dict; got {metadata!r:.200} ({e})."
            ) from None
    if torque is not None and not dynamic:
        raise ValueError("`torque` needs a rigid-body ensemble: pass `inertia` too.")
    if torque is not None:
        check_callable(torque, "torque", "torque(t, q, omega)", 3)
    if path is not None:
        path = _check_path(path)
        # Before anything is written (the writer replaces the run already in `path`): traced data
        # cannot be fetched to the host. Under `jax.jit` every value is traced, even a constant.
        inputs = {
            "q0": q0,
            "omega": omega,
            "dt": dt,
            "t0": t0,
            "inertia": inertia,
            "torque": torque,
        }
        traced = [n for n, x in inputs.items() if any(map(is_tracer, jax.tree_util.tree_leaves(x)))]
        if traced or is_tracer(jnp.zeros(())):
            what = f"`{'`, `'.join(traced)}` traced" if traced else "inside jax.jit"
            raise ValueError(
                f"`path`: a run under a JAX transformation ({what}: jax.jit, jax.vmap or a "
                "derivative) cannot be written to disk; pass path=None and keep the result in "
                "memory, or call simulate_ensemble with `path` outside the transformation."
            )

    q0 = check_trailing(q0, 4, "q0")
    omega_fn = None
    if callable(omega):
        if dynamic:
            raise ValueError(
                "`omega` must be an array of initial angular velocities for rigid bodies."
            )
        check_callable(omega, "omega", "omega(t, q)", 2)
        omega_fn = omega
        omega = jnp.zeros((3,), q0.dtype)
    omega = check_trailing(omega, 3, "omega")
    # The orientation's dtype governs, as in `integrate` and `simulate_rigid_body` (float32 bodies
    # with a float64 NumPy inertia or ω stay float32).
    dtype = q0.dtype
    shapes = [q0.shape[:-1], omega.shape[:-1]]
    if isinstance(omega_fn, Sampled):
        # Per-body samples (T, ..., 3) join the batch (laid out over the bodies below).
        samples = as_float_array(omega_fn.omegas, "omegas")
        if samples.ndim < 2 or samples.shape[-1] != 3:
            raise ValueError(
                "the samples of a `jaxquat.sampled` `omega` must have shape (T, ..., 3); got "
                f"shape {tuple(samples.shape)}."
            )
        shapes[1] = samples.shape[1:-1]
    if dynamic:
        inertia, inertia_batch = _check_inertia(inertia)
        shapes.append(inertia_batch)
    try:
        batch = tuple(np.broadcast_shapes(*shapes))
    except ValueError as e:
        names = "q0, omega" + (", inertia" if dynamic else "")
        raise ValueError(f"the leading (body) shapes of {names} do not broadcast: {shapes}.") from e
    dt_array = as_float_array(dt, "dt")
    if dt_array.ndim != 0:
        raise ValueError(f"`dt` must be a scalar; got shape {tuple(dt_array.shape)}.")
    # (Not a bool: `dt=True` ran with dt = 1, where `t0=True` was refused.)
    _check_real_scalar(dt, "dt")
    _check_real_scalar(t0, "t0")
    if not is_tracer(dt_array) and not np.isfinite(np.asarray(dt_array)):
        raise ValueError(f"`dt` must be finite; got {float(dt_array)!r}.")
    if method is None:
        method = "cf4" if dynamic else "euler"
    method = check_choice(
        method, [m for m in METHODS if not m.startswith("magnus")] if dynamic else METHODS, "method"
    )

    num_bodies = math.prod(batch)
    if num_bodies == 0:
        raise ValueError(f"the ensemble has no bodies (batch shape {batch}).")
    sharding = body_sharding(devices)
    num_devices = sharding.mesh.size
    padded = -(-num_bodies // num_devices) * num_devices
    # Times in float64 when x64 is on (as `integrate`): t_k = t0 + k·dt with the integer step k.
    time_dtype = jnp.promote_types(jnp.result_type(float), dtype)
    if torque is not None or (omega_fn is not None and not isinstance(omega_fn, Sampled)):
        # (samples are looked up by the time since their own t0)
        q, w = jax.ShapeDtypeStruct((padded, 4), dtype), jax.ShapeDtypeStruct((padded, 3), dtype)
        if torque is not None:
            reads, what = _reads_time(torque, q, w), "`torque(t, q, omega)`"
        else:
            reads, what = _reads_time(omega_fn, q), "`omega(t, q)`"
        widen = " or turn on jax_enable_x64 (float64 times)"
        check_times_advance(t0, dt, num_steps, time_dtype, what, reads, widen, method)

    def place(x, element_shape, fill):
        x = jnp.broadcast_to(x.astype(dtype), batch + element_shape)
        x = x.reshape((num_bodies,) + element_shape)
        return _pad_and_shard(x, jnp.asarray(fill, dtype), padded=padded, sharding=sharding)

    q_start = place(q0, (4,), [1.0, 0.0, 0.0, 0.0])
    omega_start = place(omega, (3,), [0.0, 0.0, 0.0])
    dt_device = jnp.asarray(dt_array, time_dtype)
    t0_device = jnp.asarray(t0, time_dtype)
    replicated = NamedSharding(sharding.mesh, PartitionSpec())
    time_eps = None
    if isinstance(omega_fn, Sampled):
        # The samples of each body, time-major (T, bodies, 3), padded and sharded as the bodies.
        count = samples.shape[0]
        # (T, *sample batch, 3) against the bodies' batch: aligned from the right, never the time axis.
        missing = len(batch) - (samples.ndim - 2)
        rows = samples.astype(dtype).reshape((count,) + (1,) * missing + samples.shape[1:])
        rows = jnp.broadcast_to(rows, (count,) + batch + (3,))
        rows = _pad_and_shard(
            rows.reshape((count, num_bodies, 3)),
            jnp.zeros((3,), dtype),
            padded=padded,
            sharding=_time_major(sharding),
            axis=1,
        )
        grid = (jnp.asarray(omega_fn.dt), jnp.asarray(omega_fn.t0))
        omega_fn = Sampled(rows, *(jax.device_put(x, replicated) for x in grid))
        # Lookups allow the round-off of the coarsest time given, as in `integrate` (`Sampled._index`).
        time_eps = max(_eps_of(x) for x in (dt_array, jnp.asarray(t0), *grid))
    if omega_fn is not None:
        _check_omega_fn(omega_fn, method, t0_device, dt_device, q_start)
    # float32 long-run mode (Kahan-compensated increments), as in `integrate` / `simulate_rigid_body`.
    compensated = method in LIE_METHODS and jnp.dtype(dtype).itemsize < 8
    if dynamic:
        if inertia_batch == ():  # one inertia for all bodies: replicated, not sharded
            replicated = NamedSharding(sharding.mesh, PartitionSpec())
            inertia_state = jax.device_put(inertia.astype(dtype), replicated)
        else:
            element = inertia.shape[len(inertia_batch) :]
            fill = np.eye(3) if element == (3, 3) else np.ones(3)
            inertia_state = place(inertia, element, fill)
        omega_body = omega_start if frame == "body" else _to_body(omega_start, q_start)
        c0 = compensations(q_start, omega_body) if compensated else None
        state = (q_start, omega_body, inertia_state, c0)  # as `simulate_rigid_body`: compensated
    else:
        c0 = jnp.zeros_like(q_start) if compensated else None
        state = (q_start, c0, omega_start)
    stats = None
    if statistics:
        zeros = jax.device_put(jnp.zeros((padded,), dtype), sharding)
        ones = jax.device_put(jnp.ones((padded,), dtype), sharding)
        # Σ angles and its compensation; the farthest rotation's |vec|² and |w| (the identity).
        stats = (zeros, zeros, zeros, ones)

    if chunk_size is None:
        chunk_size = _default_chunk(num_steps, num_bodies, save_every)
    elif save_every:
        chunk_size = save_every * max(1, -(-chunk_size // save_every))
    block = save_every or chunk_size

    if reusable_callable(omega_fn) and reusable_callable(torque):
        # The callables' arrays are dynamic arguments of the compiled chunk, replicated over the
        # devices (new values, e.g. trained parameters, do not recompile); the rest of them is static.
        omega_params, omega_static = _split_callable(omega_fn, replicated)
        torque_params, torque_static = _split_callable(torque, replicated)
        params = (omega_params, torque_params)
        run_chunk = _run_chunk
    else:
        # A function, bound method or partial may read state that changes between calls (and the
        # final ω is evaluated after the run): the chunks are compiled for this call only, with both
        # callables closed over (they need not hash; NumPy values stay NumPy).
        callables = (omega_fn, torque)
        omega_static = torque_static = None
        params = (None, None)
        run_chunk = jax.jit(
            lambda *args, **options: _run_chunk_steps(*args, **options, callables=callables),
            static_argnames=_CHUNK_STATIC,
        )
    config = dict(
        dynamic=dynamic,
        frame=frame,
        method=method,
        omega_fn=omega_static,
        time_eps=time_eps,
        torque=torque_static,
        save=save_every is not None,
        sharding=sharding,
        compensated=compensated,
        renormalize_every=_RENORMALIZE_EVERY,
        unroll=_UNROLL,
    )
    config = tuple(sorted(config.items()))

    saved_steps = list(range(0, num_steps + 1, save_every)) if save_every else []
    traced_time = is_tracer(dt) or is_tracer(t0)  # (under jax.grad / jit: no float() of them)
    if not save_every:
        times = None
    elif traced_time:
        times = t0 + dt * jnp.asarray(saved_steps, jnp.result_type(dt, t0))
    else:
        with np.errstate(over="ignore", invalid="ignore"):
            times = float(t0) + float(dt) * np.asarray(saved_steps, np.float64)
        if not np.all(np.isfinite(times)):  # (the run wrote an ensemble `load_ensemble` refused)
            k = saved_steps[int(np.argmin(np.isfinite(times)))]
            raise ValueError(
                f"`dt` = {float(dt)!r}, `t0` = {float(t0)!r}: the time t0 + k·dt of saved step "
                f"k = {k} overflows float64; use a smaller |dt| or |t0|, or fewer steps."
            )
    writer = None
    if path is not None and jax.process_index() == 0:
        index_metadata = dict(
            batch_shape=list(batch),
            dtype=jnp.dtype(dtype).name,
            dynamic=dynamic,
            frame=frame,
            method=method,
            dt=float(dt),
            t0=float(t0),
            num_steps=num_steps,
            save_every=save_every,
            num_bodies=num_bodies,
            num_devices=num_devices,
        )
        if metadata is not None:
            index_metadata["run"] = metadata
        # Numbers per body in the `.npy` files: the saved states (with ω for rigid bodies), then
        # `finish`'s final q, ω and angle from the start (and the two statistics).
        numbers = len(saved_steps) * (7 if dynamic else 4) + 8 + (2 if statistics else 0)
        needed = numbers * num_bodies * jnp.dtype(dtype).itemsize
        writer = _StateWriter(path, index_metadata, needed=needed)

    layout = _batch_layout(batch, sharding.mesh) if padded == num_bodies else None

    def unpad_time_major(x, width):
        if isinstance(x, np.ndarray):  # (fetched to be written)
            return x[:, :num_bodies].reshape((x.shape[0],) + batch + (width,))
        return _unpadded(x, num_bodies, batch, layout, time_major=True)

    def keep_or_write(saved, steps, steps_done):
        nonlocal kept, num_kept
        if writer is not None:
            _refuse_traced(saved[0], writer.path)
            arrays = {"states": unpad_time_major(_to_host(saved[0]), 4)}
            if dynamic:
                arrays["omegas"] = unpad_time_major(_to_host(saved[1]), 3)
            writer.write_record(arrays, steps, steps_done=steps_done)
        elif path is None:
            if kept is None:
                kept = _start_kept(saved, len(saved_steps))
            else:
                kept = _keep_at(kept, saved, jnp.asarray(num_kept, jnp.int32))
            num_kept += saved[0].shape[0]

    kept: tuple[Array, ...] | None = None
    num_kept = 0
    if save_every:
        initial = (q_start, omega_start) if dynamic else (q_start,)
        keep_or_write(tuple(x[None] for x in initial), [0], 0)

    bar = None
    if progress is True:
        from tqdm.auto import tqdm

        bar = tqdm(total=num_steps, unit="step", file=sys.stderr, desc="ensemble", leave=False)

    def finish_chunk(pending):
        chunk_state, saved, steps, steps_done = pending
        if saved is not None:
            keep_or_write(saved, steps, steps_done)
        else:
            jax.block_until_ready(chunk_state)
            if writer is not None:
                writer.progress(steps_done)
        if bar is not None:
            bar.update(steps_done - bar.n)
        elif callable(progress) and progress is not True:
            progress(steps_done, num_steps)

    starts = list(range(0, num_steps, chunk_size))
    pending = None
    try:
        for start in starts:
            length = min(chunk_size, num_steps - start)
            n_blocks, tail = divmod(length, block)
            state, stats, saved = run_chunk(
                state,
                stats,
                q_start,
                dt_device,
                t0_device,
                jnp.asarray(start, jnp.int32),
                params,
                n_blocks=n_blocks,
                block=block,
                tail=tail,
                config=config,
            )
            steps = [s for s in saved_steps if start < s <= start + length]
            # Dispatch is asynchronous: the next chunk computes while the host handles this one.
            if pending is not None:
                finish_chunk(pending)
            pending = (state, saved, steps, start + length)
        if pending is not None:
            finish_chunk(pending)
    finally:
        if bar is not None:
            bar.close()

    def unpad(x):
        return _unpadded(x, num_bodies, batch, layout, time_major=False)

    final = state[0]
    if dynamic:
        final_omega = state[1] if frame == "body" else _to_world(state[1], final)
    elif omega_fn is not None:
        source, t_start = _omega_source(omega_fn, t0_device, dt_device, time_eps)
        t_end = t_start + jnp.asarray(num_steps, time_dtype) * dt_device
        final_omega = jnp.broadcast_to(source(t_end, final), final.shape[:-1] + (3,)).astype(dtype)
    else:
        final_omega = omega_start
    angle_from_start = _angle_between(q_start, final)
    final, final_omega, angle_from_start = unpad(final), unpad(final_omega), unpad(angle_from_start)
    total_angle = unpad(stats[0]) if statistics else None
    max_angle = unpad(jax.jit(_farthest_angle)(*stats[2:])) if statistics else None
    saved_q = saved_w = None
    if kept is not None:
        saved_q = unpad_time_major(kept[0], 4)
        if dynamic:
            saved_w = unpad_time_major(kept[1], 3)
    if writer is not None:
        arrays = {"final": final, "final_omega": final_omega, "angle_from_start": angle_from_start}
        if statistics:
            arrays.update(total_angle=total_angle, max_angle_from_start=max_angle)
        _refuse_traced(final, writer.path)
        writer.finish({k: _to_host(v) for k, v in arrays.items()})
    jax.block_until_ready((final, final_omega))
    return EnsembleResult(
        final=final,
        final_omega=final_omega,
        saved=saved_q,
        saved_omega=saved_w,
        times=times,
        angle_from_start=angle_from_start,
        total_angle=total_angle,
        max_angle_from_start=max_angle,
        num_steps=num_steps,
        num_chunks=len(starts),
        path=None if path is None else os.fspath(path),
        seconds=time.perf_counter() - started,
    )
