"""The benchmark suite: jaxquat's integrators against SciPy, numpy-quaternion, jaxlie and plain JAX.

Run it as `python -m jaxquat bench [--preset quick|full] [--output DIR]` or
`python benchmarks/run.py [...]`; the entry point is `main(argv)`.

Workloads (N bodies, T steps of Δt, world frame, every result checked against a closed form before
it is timed — a fast wrong answer does not count):

- **W1** constant per-body ω, keep only the final orientation;
- **W2** the same, keep the whole time-major trajectory `(T + 1, N, 4)`;
- **W3** ω sampled per step from a time-major `(T, N, 3)` array (piecewise constant). The samples are
  those of a two-axis motion q(t) = exp(a t) ⊗ exp(b t) ⊗ q₀, so the exact final orientation is known;
- **W4** coning ω(t) given as a function: work–precision (final error against the closed form vs wall
  time) of jaxquat's methods and diffrax solvers, numpy-quaternion's DOP853 integrator and stock
  diffrax Tsit5 → a PNG;
- **W5** `jax.grad` of a loss on the final orientations w.r.t. all ω (constant ω of W1 and sampled ω
  of W3), time relative to the forward pass.

Hygiene: every JAX contender is compiled ahead of time (compile time reported
separately), results are blocked on (`block_until_ready`), contenders of one row are timed
interleaved, in alternating order, and the median of the repeats is reported, as body-steps per second
and as the ratio to the best peer of the row. Peers that would take longer than the preset's budget
per call are timed on fewer steps (marked †; their cost per step is constant, so the rate is
unaffected; in W2, whose cost per step grows with the trajectory's size on a virtual machine, the
peers that fit a larger budget run all T steps) — jaxquat is always timed on all T steps. Peers are imported lazily and skipped, with a
note, when they are not installed.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import io
import json
import math
import os
import platform
import re
import statistics
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

# ----------------------------------------------------------------------------------------------------
# Huge pages

HUGE_PAGES_TUNABLE = "glibc.malloc.hugetlb=1"


def huge_pages_status() -> str:
    """How large buffers are backed in this process, for the record."""
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    try:
        with open("/sys/kernel/mm/transparent_hugepage/enabled") as f:
            mode = f.read().split("[", 1)[1].split("]", 1)[0]
    except (OSError, IndexError):
        return "unknown (no transparent huge pages)"
    if mode == "always":
        return "transparent huge pages: always"
    if mode == "never":
        return "transparent huge pages: never"
    via = "glibc.malloc.hugetlb=1" if HUGE_PAGES_TUNABLE in tunables else "not for malloc"
    return f"transparent huge pages: madvise (NumPy madvises its arrays; malloc/XLA: {via})"


def relaunch_with_huge_pages(command: Sequence[str]) -> None:
    """Re-run this process as `python *command` with glibc's huge-page tunable set, once.

    Every contender's large buffers then live on 2 MiB pages. NumPy madvises huge pages for its own
    arrays; XLA's CPU buffers come from malloc, which madvises them only with this tunable (glibc ≥
    2.35, read at start-up, hence the relaunch). Without it, a 3.2 GB W2 trajectory costs ~780,000
    page faults (≈ 2 s of kernel time) per call in every JAX contender, none in NumPy's. Returns
    without relaunching on other platforms, when the tunable is already set, or with
    `--no-huge-pages`.
    """
    if "--no-huge-pages" in command or sys.platform != "linux":
        return
    libc, version = platform.libc_ver()
    try:
        new_enough = libc == "glibc" and tuple(int(v) for v in version.split(".")[:2]) >= (2, 35)
    except ValueError:
        new_enough = False
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    if not new_enough or HUGE_PAGES_TUNABLE in tunables:
        return
    environment = dict(os.environ)
    environment["GLIBC_TUNABLES"] = ":".join(t for t in (tunables, HUGE_PAGES_TUNABLE) if t)
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *command], environment)


# ----------------------------------------------------------------------------------------------------
# Configuration


# W4 sweeps that are dense around each method's crossing of W4_TARGET_ERROR (1e-8 rad), so the time
# at the target is interpolated between neighbours a few per cent apart in steps (fourth-order
# methods: error ∝ steps⁻⁴; magnus4 crosses near 480 steps, cf4 near 360; the sixth-order magnus6
# near 92, the eighth-order magnus8 near 52) or ~1.4× apart in tolerance
# (Tsit5 and RKMK45 cross near 3.4e-9, numpy-quaternion's DOP853 near 6.5e-9). The outer points
# anchor the plot and keep the crossing bracketed. Each step count of a fixed-step method is a
# compilation (~0.4 s), so only the neighbours of the crossing are dense.
_W4_DENSE_STEPS = (256, 448, 480, 512, 1024)
_W4_DENSE_TOLERANCES = (1e-7, 1e-8, 7e-9, 5e-9, 3.5e-9, 2.5e-9, 1e-9)
W4_DENSE_SWEEPS: tuple[tuple[str, tuple[float, ...]], ...] = (
    ("jaxquat integrate magnus4", _W4_DENSE_STEPS),
    ("jaxquat integrate magnus6", (64, 88, 96, 128)),
    ("jaxquat integrate magnus8", (32, 48, 52, 56, 64)),
    ("jaxquat diffrax Magnus8", (32, 48, 52, 56, 64)),
    ("jaxquat diffrax Magnus6", (64, 88, 96, 128)),
    ("jaxquat integrate cf4", (256, 352, 384, 512)),
    ("jaxquat diffrax Magnus4", _W4_DENSE_STEPS),
    ("diffrax Tsit5 (stock)", _W4_DENSE_TOLERANCES + (1e-10,)),
    ("jaxquat diffrax RKMK45", _W4_DENSE_TOLERANCES + (1e-10,)),
    ("numpy-quaternion integrate_angular_velocity", _W4_DENSE_TOLERANCES),
)

# The quick preset compiles, for each fixed-step `integrate` method (one compilation per step count),
# only two step counts that bracket its crossing of 1e-8 rad and one coarser count for the plot's
# slope. The errors are deterministic: magnus4 1.32e-8 / 7.7e-9 at 448 / 512 steps (480 gives
# 9.99e-9, too close to the target to bracket it safely), magnus6 1.3e-8 / 7.5e-9 at 88 / 96, magnus8
# 1.8e-8 / 9.4e-9 at 48 / 52, cf4 1.1e-8 / 7.4e-9 at 352 / 384. The diffrax solvers compile once for
# all their step sizes and tolerances and keep the dense sweeps.
_W4_QUICK_STEPS = {
    "jaxquat integrate magnus4": (256, 448, 512),
    "jaxquat integrate magnus6": (64, 88, 96),
    "jaxquat integrate magnus8": (32, 48, 52),
    "jaxquat integrate cf4": (256, 352, 384),
}
W4_QUICK_SWEEPS = tuple(
    (name, _W4_QUICK_STEPS.get(name, values)) for name, values in W4_DENSE_SWEEPS
)


def _with_wide(sweeps, steps, tolerances):
    """Dense sweeps merged with a preset's wide grids (steps ascending, tolerances descending)."""
    merged = []
    for name, values in sweeps:
        if any(isinstance(v, float) for v in values):
            merged.append((name, tuple(sorted(set(values) | set(tolerances), reverse=True))))
        else:
            merged.append((name, tuple(sorted(set(values) | set(steps)))))
    return tuple(merged)


_FULL_W4_STEPS = (16, 32, 64, 128, 256, 512, 1024, 2048, 4096, 8192, 16384)
_FULL_W4_TOLERANCES = (1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12, 1e-13)


@dataclasses.dataclass(frozen=True)
class Preset:
    """What one run of the suite measures."""

    sizes: tuple[int, ...]  # numbers of bodies N for W1–W3
    num_steps: int  # T
    dtypes: tuple[str, ...]
    repeats: int  # interleaved timing rounds per row (the median is reported)
    budget: float  # seconds one timed call of a peer may take before it is timed on fewer steps
    workloads: tuple[str, ...]
    w4_steps: tuple[int, ...]  # step counts swept by the fixed-step methods in W4
    w4_tolerances: tuple[float, ...]  # tolerances swept by the adaptive methods in W4
    w4_repeats: int
    w5_sizes: tuple[int, ...]
    reference: bool  # also time the tuned hand-written JAX loop (not a peer; a yardstick)
    w4_methods: tuple[str, ...] = (  # `integrate`
        "euler",
        "midpoint",
        "magnus4",
        "magnus6",
        "magnus8",
        "cf4",
    )
    w4_solvers: tuple[str, ...] = (
        "LieEuler",
        "ExpMidpoint",
        "Magnus4",
        "Magnus6",
        "Magnus8",
        "CF4",
        "RKMK45",
    )
    # W4 sweeps of single methods, by series name, instead of `w4_steps` / `w4_tolerances` (e.g.
    # dense around each method's crossing of the target error).
    w4_sweeps: tuple[tuple[str, tuple[float, ...]], ...] = ()
    w5_dtypes: tuple[str, ...] | None = None  # None: the same as `dtypes`
    w5_variants: tuple[str, ...] = ("constant", "sampled")  # which ω W5 differentiates w.r.t.
    sample_seconds: float = 0.01  # shorter calls are repeated within one timing sample
    # W2's check: None compares every body at every step with the closed form; n compares n bodies
    # spread over the batch at every step and every body at a few steps (`check_bodies`, `check_steps`).
    w2_check_bodies: int | None = None
    # W2: a peer whose call on all T steps would take at most this long runs all T steps, as jaxquat
    # does; slower peers keep `budget`. A W2 call writes a (steps + 1, N, 4) trajectory, and on a
    # virtual machine fresh memory costs more per byte the more of it there is, so a fast peer timed on
    # fewer steps (a smaller buffer) would look faster per step than it is.
    w2_budget: float | None = None
    # W5 at larger N times jaxquat alone (a peer's sampled gradient at N = 10⁵ takes 8-15 s) and checks
    # its gradient on the `check_bodies` subset against the hand-written loop's gradient of those
    # bodies (the loss is a sum over bodies, so each body's rows depend on that body alone).
    w5_peers_max_bodies: int | None = None


PRESETS: dict[str, Preset] = {
    # For the smoke test: every code path, tiny sizes, seconds.
    "micro": Preset(
        sizes=(3,),
        num_steps=20,
        dtypes=("float64", "float32"),
        repeats=2,
        budget=0.2,
        workloads=("W1", "W2", "W3", "W4", "W5"),
        w4_steps=(256,),
        w4_tolerances=(1e-9,),
        w4_repeats=1,
        w5_sizes=(3,),
        reference=True,
        w4_methods=("euler", "magnus4", "magnus6"),
        w4_solvers=("Magnus4",),
        w5_dtypes=("float64",),
        w5_variants=("sampled",),
        sample_seconds=0.002,
    ),
    "quick": Preset(
        sizes=(100_000,),
        num_steps=1000,
        dtypes=("float64",),
        repeats=3,
        budget=0.2,
        workloads=("W1", "W2", "W3", "W4", "W5"),
        w4_steps=(64, 256, 1024),  # euler and midpoint (far from 1e-8: context for the plot)
        w4_tolerances=(1e-6, 1e-9, 1e-12),
        w4_repeats=3,
        # W5 at N = 10⁵ (jaxquat alone above 10³) takes 20-35 s on the 2-core VM, which would put the
        # preset over two minutes: `--workloads W5 --w5-sizes 100000` measures it on its own.
        w5_sizes=(1000,),
        w5_peers_max_bodies=1000,
        reference=False,
        w2_check_bodies=512,
        w2_budget=2.0,
        w4_methods=("euler", "midpoint", "magnus4", "magnus6", "magnus8", "cf4"),
        w4_solvers=("Magnus4", "Magnus6", "Magnus8", "RKMK45"),
        w4_sweeps=W4_QUICK_SWEEPS,
    ),
    "full": Preset(
        sizes=(1, 1000, 100_000),
        num_steps=1000,
        dtypes=("float64", "float32"),
        repeats=5,
        budget=12.0,
        workloads=("W1", "W2", "W3", "W4", "W5"),
        w4_steps=_FULL_W4_STEPS,
        w4_tolerances=_FULL_W4_TOLERANCES,
        w4_repeats=5,
        w5_sizes=(1, 1000, 100_000),
        reference=True,
        w4_sweeps=_with_wide(W4_DENSE_SWEEPS, _FULL_W4_STEPS, _FULL_W4_TOLERANCES),
    ),
}

DT = 0.01  # s; with the sampled rates below |ω|Δt is a few 1e-2 rad per step, typical of real data
# Maximum angle error (rad) of a final orientation against the closed form, and of |q| − 1.
ERROR_TOLERANCE = {"float64": 1e-9, "float32": 2e-3}
NORM_TOLERANCE = {"float64": 1e-9, "float32": 1e-3}
W4_TARGET_ERROR = 1e-8

# ----------------------------------------------------------------------------------------------------
# Independent quaternion helpers (generic over numpy / jax.numpy; used for the references and by the
# hand-written peers, never jaxquat's own code).


def _q_mul(p, q, xp):
    pw, px, py, pz = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return xp.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def _q_conj(q, xp):
    return xp.concatenate([q[..., :1], -q[..., 1:]], axis=-1)


def _q_exp(v, xp):
    """Unit quaternion of the rotation vector v (series below θ² = 1e-8, NaN-free gradients)."""
    theta_sq = xp.sum(v * v, axis=-1)
    small = theta_sq < 1e-8
    theta = xp.sqrt(xp.where(small, 1.0, theta_sq))
    real = xp.where(small, 1.0 - theta_sq / 8.0, xp.cos(0.5 * theta))
    imag = xp.where(small, 0.5 - theta_sq / 48.0, xp.sin(0.5 * theta) / theta)
    return xp.concatenate([real[..., None], imag[..., None] * v], axis=-1)


def _q_log(q, xp):
    """Rotation vector of the unit quaternion q (shortest rotation)."""
    q = xp.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    s_sq = xp.sum(v * v, axis=-1)
    small = s_sq < 1e-24
    s = xp.sqrt(xp.where(small, 1.0, s_sq))
    coef = xp.where(small, 2.0 / q[..., 0], 2.0 * xp.arctan2(s, q[..., 0]) / s)
    return coef[..., None] * v


def _q_rotate(q, v, xp):
    zero = xp.zeros_like(v[..., :1])
    return _q_mul(_q_mul(q, xp.concatenate([zero, v], axis=-1), xp), _q_conj(q, xp), xp)[..., 1:]


def angle_error(p, q) -> np.ndarray:
    """Geodesic angle (rad) between the rotations p and q, computed in float64 (sign-invariant)."""
    p = np.asarray(p, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    r = _q_mul(_q_conj(q, np), p, np)
    return 2.0 * np.arctan2(np.linalg.norm(r[..., 1:], axis=-1), np.abs(r[..., 0]))


def _loss(q_final, target, xp):
    """Σ |vec(r* ⊗ q)|²: smooth, sign-invariant loss on final orientations (docs/numerics.md §4)."""
    r = _q_mul(_q_conj(target, xp), q_final, xp)
    return xp.sum(r[..., 1:] * r[..., 1:])


# ----------------------------------------------------------------------------------------------------
# Problems


@dataclasses.dataclass
class Problem:
    """The data of one W1–W3 row and its closed-form answers."""

    workload: str
    dtype: str
    num_bodies: int
    num_steps: int
    q0: np.ndarray  # (N, 4) in `dtype`
    omega: np.ndarray  # (N, 3): W1/W2 the constant ω in `dtype`; W3 the first axis a (float64)
    spin: np.ndarray | None  # (N, 3): W3 the second axis b
    omegas: Any = None  # W3: (T, N, 3) samples, a jax array in `dtype`
    dt: float = DT
    _closed_form: dict = dataclasses.field(default_factory=dict, repr=False)  # W2 check's cache

    def expected(self, num_steps: int) -> np.ndarray:
        """Closed-form final orientations after `num_steps` steps, float64 `(N, 4)`."""
        q0 = self.q0.astype(np.float64)
        t = num_steps * self.dt
        rotation = _q_exp(self.omega.astype(np.float64) * t, np)
        if self.spin is not None:
            rotation = _q_mul(rotation, _q_exp(self.spin * t, np), np)
        return _q_mul(rotation, q0, np)

    def trajectory_check(
        self, qs: np.ndarray, bodies: int | None = None, chunk: int = 64
    ) -> tuple[float, float]:
        """(max angle error, max ||q| − 1|) of a time-major trajectory `(K + 1, N, 4)` against the
        closed form. `bodies=None` checks every body at every step; `bodies=n` checks the
        n bodies of `check_bodies` at every step and every body at the steps of `check_steps`.
        The closed-form values are kept on the problem, so the contenders of a row share them."""
        num_steps, num_bodies = qs.shape[0] - 1, qs.shape[1]
        q0 = self.q0.astype(np.float64)
        omega = self.omega.astype(np.float64)
        worst = [0.0, 0.0]

        def expected(steps, index):
            k = np.asarray(steps, dtype=np.float64)[:, None, None]
            return _q_mul(_q_exp(k * self.dt * omega[index][None], np), q0[index][None], np)

        def visit(block, reference):
            block = np.asarray(block, dtype=np.float64)
            worst[0] = max(worst[0], float(np.max(angle_error(block, reference))))
            norm = np.abs(np.linalg.norm(block, axis=-1) - 1.0)
            worst[1] = max(worst[1], float(np.max(norm)))

        if bodies is None:
            for start in range(0, num_steps + 1, chunk):
                stop = min(start + chunk, num_steps + 1)
                visit(qs[start:stop], expected(range(start, stop), slice(None)))
            return worst[0], worst[1]
        cache = self._closed_form
        index = check_bodies(num_bodies, bodies)
        key = ("bodies", bodies)
        if key not in cache or cache[key].shape[0] < num_steps + 1:
            cache[key] = np.concatenate(
                [
                    expected(range(start, min(start + chunk, num_steps + 1)), index)
                    for start in range(0, num_steps + 1, chunk)
                ]
            )
        visit(qs[:, index], cache[key][: num_steps + 1])
        steps = check_steps(num_steps)
        for k in steps:
            if ("step", k) not in cache:
                cache["step", k] = expected([k], slice(None))[0]
        visit(qs[steps], np.stack([cache["step", k] for k in steps]))
        return worst[0], worst[1]


def check_bodies(num_bodies: int, count: int) -> np.ndarray:
    """The bodies whose whole trajectory a subset check of W2 compares with the closed form: the
    first and last 8 (vector-lane and chunk remainders) and the rest spread evenly over the batch
    with an odd stride."""
    if count >= num_bodies:
        return np.arange(num_bodies)
    ends = np.r_[0:8, num_bodies - 8 : num_bodies]
    spread = max(count - 16, 2)
    stride = max(1, (num_bodies - 1) // (spread - 1))
    stride -= 1 if stride > 1 and stride % 2 == 0 else 0  # odd: every lane residue is visited
    return np.unique(np.clip(np.r_[ends, np.arange(spread) * stride], 0, num_bodies - 1))


def check_steps(num_steps: int) -> list[int]:
    """The steps at which a subset check of W2 compares every body with the closed form: the first
    few, the last few and 17 spread over the run (block and chunk boundaries fall anywhere)."""
    steps = {0, 1, 2, 3, num_steps - 1, num_steps, *np.linspace(0, num_steps, 17).round()}
    return sorted(int(k) for k in steps if 0 <= k <= num_steps)


def _sampled_rates(a, b, dt, num_steps):
    """The piecewise-constant ω_k (k = 0..T−1, time-major) that maps q_k to q_{k+1} exactly for
    q(t) = exp(a t) ⊗ exp(b t) ⊗ q₀: ω_k = log(exp(R(exp(a t_{k+1})) b Δt) ⊗ exp(a Δt))/Δt.

    exp(a Δt) commutes with exp(a t), so the step is exp(b Δt) ⊗ exp(a Δt) conjugated by
    exp(a t_{k+1}) and ω_k = R(exp(a t_{k+1})) ω*, ω* = log(exp(b Δt) ⊗ exp(a Δt))/Δt: a constant
    vector turned about a, evaluated per step by Rodrigues' formula (one cos and sin of |a| t_{k+1}).
    The (T, N, 3) samples of an N = 10⁵ row then cost seconds, not tens of seconds."""
    import jax
    import jax.numpy as jnp

    @jax.jit
    def rates(a, b):
        fixed = _q_log(_q_mul(_q_exp(b * dt, jnp), _q_exp(a * dt, jnp), jnp), jnp) / dt  # ω*
        norm_a = jnp.sqrt(jnp.sum(a * a, axis=-1))
        axis = a / jnp.where(norm_a > 0, norm_a, 1.0)[:, None]
        along = axis * jnp.sum(axis * fixed, axis=-1)[:, None]  # ω* along a, across it, a × ω*
        across = fixed - along
        turned = jnp.cross(axis, fixed)
        # |a| t_{k+1} for k = 0..T−1: the angle exp(a t_{k+1}) turns ω* by.
        angle = jnp.arange(1, num_steps + 1, dtype=a.dtype)[:, None] * dt * norm_a[None]
        c, s = jnp.cos(angle)[..., None], jnp.sin(angle)[..., None]
        return along[None] + c * across[None] + s * turned[None]  # one fused (T, N, 3) pass

    return rates(jnp.asarray(a, dtype=jnp.float64), jnp.asarray(b, dtype=jnp.float64))


def make_problem(
    workload: str, dtype: str, num_bodies: int, num_steps: int, seed: int = 0
) -> Problem:
    """Random initial orientations and rates (N(0, 2²) rad/s per component) for one row."""
    import jax.numpy as jnp

    rng = np.random.default_rng([seed, num_bodies, num_steps, int(workload[1:])])
    q0 = rng.normal(size=(num_bodies, 4))
    q0 /= np.linalg.norm(q0, axis=-1, keepdims=True)
    omega = 2.0 * rng.normal(size=(num_bodies, 3))
    spin = None
    omegas = None
    if workload == "W3":
        spin = 2.0 * rng.normal(size=(num_bodies, 3))
        omegas = _sampled_rates(omega, spin, DT, num_steps).astype(jnp.dtype(dtype))
        omegas.block_until_ready()  # made before any contender is timed
    return Problem(
        workload=workload,
        dtype=dtype,
        num_bodies=num_bodies,
        num_steps=num_steps,
        q0=q0.astype(dtype),
        # W3: the closed form must use the a the samples were made from (float64); rounding it to
        # float32 moved exp(aT) ⊗ exp(bT) ⊗ q₀ by up to 2.3e-6 rad at T = 1,000 (the float32 errors).
        omega=omega if workload == "W3" else omega.astype(dtype),
        spin=spin,
        omegas=omegas,
    )


# ----------------------------------------------------------------------------------------------------
# Contenders for W1–W3


@dataclasses.dataclass
class Runner:
    """One contender compiled for one row: `run()` does the work once and returns the orientations."""

    run: Callable[[], Any]
    compile_seconds: float | None = None


@dataclasses.dataclass(frozen=True)
class Contender:
    name: str
    role: str  # "jaxquat", "peer" or "reference" (a yardstick, not counted as a peer)
    make: Callable[[Problem, int], Runner]  # (problem, steps to run) → runner
    workloads: tuple[str, ...]
    requires: tuple[str, ...] = ()  # importable modules it needs
    is_jax: bool = True
    note: str = ""


def _compiled(function, *args) -> Runner:
    """Compile `function(*args)` ahead of time; the runner calls the executable."""
    import jax

    start = time.perf_counter()
    compiled = jax.jit(function).lower(*args).compile()
    seconds = time.perf_counter() - start
    return Runner(run=lambda: compiled(*args), compile_seconds=seconds)


def _jax_inputs(problem: Problem, num_steps: int):
    import jax.numpy as jnp

    q0 = jnp.asarray(problem.q0)
    if problem.workload == "W3":
        omegas = problem.omegas
        return q0, (omegas if num_steps == omegas.shape[0] else omegas[:num_steps])
    return q0, jnp.asarray(problem.omega)


def _load_integrate():
    from . import _integrate

    return _integrate.integrate, _integrate.sampled


def _make_jaxquat(problem: Problem, num_steps: int) -> Runner:
    integrate, sampled = _load_integrate()
    dt = problem.dt
    save = "all" if problem.workload == "W2" else "final"
    if problem.workload == "W3":

        def function(q0, omegas):
            return integrate(q0, sampled(omegas, dt), dt, num_steps, save=save)

    else:

        def function(q0, omega):
            return integrate(q0, omega, dt, num_steps, save=save)

    return _compiled(function, *_jax_inputs(problem, num_steps))


def _make_jax_loop(problem: Problem, num_steps: int) -> Runner:
    """The plain hand-written loop: lax.scan over time, an `(N, 4)` carry, exp map per step."""
    import jax.numpy as jnp
    from jax import lax

    dt = problem.dt

    def advance(q, omega):
        return _q_mul(_q_exp(omega * dt, jnp), q, jnp)

    if problem.workload == "W3":

        def function(q0, omegas):
            return lax.scan(lambda q, w: (advance(q, w), None), q0, omegas)[0]

    elif problem.workload == "W2":

        def function(q0, omega):
            # One buffer: each iteration emits its input state (q₀ … q_T; the last step is unused).
            body = lambda q, _: (advance(q, omega), q)  # noqa: E731
            return lax.scan(body, q0, None, length=num_steps + 1)[1]

    else:

        def function(q0, omega):
            return lax.scan(lambda q, _: (advance(q, omega), None), q0, None, length=num_steps)[0]

    return _compiled(function, *_jax_inputs(problem, num_steps))


def _make_jax_tuned(problem: Problem, num_steps: int) -> Runner:
    """The tuned hand-written loop (benchmarks/README.md): step hoisted, structure-of-arrays carry, unroll=8."""
    import jax.numpy as jnp
    from jax import lax

    dt = problem.dt

    def function(q0, omega):
        sw, sx, sy, sz = (c for c in jnp.moveaxis(_q_exp(omega * dt, jnp), -1, 0))

        def body(carry, _):
            w, x, y, z = carry
            return (
                sw * w - sx * x - sy * y - sz * z,
                sw * x + sx * w + sy * z - sz * y,
                sw * y - sx * z + sy * w + sz * x,
                sw * z + sx * y - sy * x + sz * w,
            ), None

        carry = tuple(jnp.moveaxis(q0, -1, 0))
        carry, _ = lax.scan(body, carry, None, length=num_steps, unroll=8)
        return jnp.stack(carry, axis=-1)

    return _compiled(function, *_jax_inputs(problem, num_steps))


def _make_jaxlie(problem: Problem, num_steps: int) -> Runner:
    """jaxlie as its docs suggest: per-body `SO3.exp(ω dt) @ R`, vmapped over bodies, scanned over time."""
    import jax
    import jaxlie
    from jax import lax

    dt = problem.dt
    advance = jax.vmap(lambda q, w: (jaxlie.SO3.exp(w * dt) @ jaxlie.SO3(q)).wxyz)

    if problem.workload == "W3":

        def function(q0, omegas):
            return lax.scan(lambda q, w: (advance(q, w), None), q0, omegas)[0]

    elif problem.workload == "W2":

        def function(q0, omega):
            # One buffer: each iteration emits its input state (q₀ … q_T; the last step is unused).
            body = lambda q, _: (advance(q, omega), q)  # noqa: E731
            return lax.scan(body, q0, None, length=num_steps + 1)[1]

    else:

        def function(q0, omega):
            return lax.scan(lambda q, _: (advance(q, omega), None), q0, None, length=num_steps)[0]

    return _compiled(function, *_jax_inputs(problem, num_steps))


def _numpy_rates(problem: Problem, num_steps: int):
    if problem.workload == "W3":
        return np.asarray(problem.omegas[:num_steps])
    return problem.omega


def _make_scipy(precomputed: bool):
    def make(problem: Problem, num_steps: int) -> Runner:
        from scipy.spatial.transform import Rotation

        dt = problem.dt
        q0 = problem.q0
        rates = _numpy_rates(problem, num_steps)

        def run():
            r = Rotation.from_quat(q0, scalar_first=True)
            trajectory = None
            if problem.workload == "W2":
                trajectory = np.empty((num_steps + 1,) + q0.shape, dtype=np.float64)
                trajectory[0] = q0
            step = Rotation.from_rotvec(rates * dt) if precomputed else None
            for k in range(num_steps):
                if problem.workload == "W3":
                    r = Rotation.from_rotvec(rates[k] * dt) * r
                else:
                    r = (step if precomputed else Rotation.from_rotvec(rates * dt)) * r
                if trajectory is not None:
                    trajectory[k + 1] = r.as_quat(scalar_first=True)
            return trajectory if trajectory is not None else r.as_quat(scalar_first=True)

        return Runner(run=run)

    return make


def _make_numpy_quaternion(precomputed: bool):
    def make(problem: Problem, num_steps: int) -> Runner:
        import quaternion

        dt = problem.dt
        q0 = quaternion.as_quat_array(np.ascontiguousarray(problem.q0, dtype=np.float64))
        rates = _numpy_rates(problem, num_steps)

        def run():
            if problem.workload == "W2":
                trajectory = np.empty((num_steps + 1,) + q0.shape, dtype=quaternion.quaternion)
                trajectory[0] = q0
                step = quaternion.from_rotation_vector(rates * dt) if precomputed else None
                for k in range(num_steps):
                    s = step if precomputed else quaternion.from_rotation_vector(rates * dt)
                    np.multiply(s, trajectory[k], out=trajectory[k + 1])
                return quaternion.as_float_array(trajectory)
            q = q0.copy()
            if problem.workload == "W3":
                for k in range(num_steps):
                    q = quaternion.from_rotation_vector(rates[k] * dt) * q
            elif precomputed:
                step = quaternion.from_rotation_vector(rates * dt)
                for _ in range(num_steps):
                    np.multiply(step, q, out=q)
            else:
                for _ in range(num_steps):
                    q = quaternion.from_rotation_vector(rates * dt) * q
            return quaternion.as_float_array(q)

        return Runner(run=run)

    return make


CONTENDERS: tuple[Contender, ...] = (
    Contender("jaxquat", "jaxquat", _make_jaxquat, ("W1", "W2", "W3")),
    Contender(
        "SciPy Rotation",
        "peer",
        _make_scipy(precomputed=False),
        ("W1", "W2", "W3"),
        requires=("scipy",),
        is_jax=False,
        note="`Rotation.from_rotvec(ω dt) * r` per step, batched; float64 internally",
    ),
    Contender(
        "SciPy, step precomputed",
        "peer",
        _make_scipy(precomputed=True),
        ("W1", "W2"),
        requires=("scipy",),
        is_jax=False,
        note="`s = Rotation.from_rotvec(ω dt)` once, then `s * r` per step",
    ),
    Contender(
        "numpy-quaternion",
        "peer",
        _make_numpy_quaternion(precomputed=False),
        ("W1", "W2", "W3"),
        requires=("quaternion",),
        is_jax=False,
        note="`from_rotation_vector(ω dt) * q` per step, vectorised over bodies; float64 internally",
    ),
    Contender(
        "numpy-quaternion, step precomputed",
        "peer",
        _make_numpy_quaternion(precomputed=True),
        ("W1", "W2"),
        requires=("quaternion",),
        is_jax=False,
        note="step quaternion formed once, then `np.multiply(s, q, out=...)` per step",
    ),
    Contender(
        "jaxlie",
        "peer",
        _make_jaxlie,
        ("W1", "W2", "W3"),
        requires=("jaxlie",),
        note="`SO3.exp(ω dt) @ R` under jit + vmap (bodies) + scan (time)",
    ),
    Contender(
        "JAX loop",
        "peer",
        _make_jax_loop,
        ("W1", "W2", "W3"),
        note="plain hand-written exp-map step in `lax.scan`, `(N, 4)` carry",
    ),
    Contender(
        "ref: tuned JAX",
        "reference",
        _make_jax_tuned,
        ("W1",),
        note="hand-written, step hoisted, structure-of-arrays carry, `unroll=8` (a yardstick, not a peer)",
    ),
)


# ----------------------------------------------------------------------------------------------------
# Timing


def _block(x):
    import jax

    return jax.block_until_ready(x)


def _timed(run: Callable[[], Any]) -> tuple[float, Any]:
    start = time.perf_counter()
    out = _block(run())
    return time.perf_counter() - start, out


def _missing(modules: Sequence[str]) -> str | None:
    import importlib.util

    for module in modules:
        if importlib.util.find_spec(module) is None:
            return module
    return None


def _check(problem: Problem, steps: int, out, w2_bodies: int | None = None) -> tuple[float, float]:
    """(max angle error against the closed form, max ||q| − 1|) of a contender's result; W2 on every
    body at every step, or with `w2_bodies` on that many bodies at every step and every body at
    the steps of `check_steps` (every contender of a row is checked the same way)."""
    out = np.asarray(out)
    if problem.workload == "W2":
        expected_shape = (steps + 1, problem.num_bodies, 4)
        if out.shape != expected_shape:
            raise ValueError(f"trajectory of shape {out.shape}, expected {expected_shape}")
        return problem.trajectory_check(out, w2_bodies)
    if out.shape != (problem.num_bodies, 4):
        raise ValueError(f"result of shape {out.shape}, expected {(problem.num_bodies, 4)}")
    error = float(np.max(angle_error(out, problem.expected(steps))))
    norm = float(np.max(np.abs(np.linalg.norm(out.astype(np.float64), axis=-1) - 1.0)))
    return error, norm


def run_row(problem: Problem, preset: Preset, log: Callable[[str], None]) -> dict:
    """Check, compile and time every contender of one W1–W3 row, interleaved; returns the row record."""
    T, N = problem.num_steps, problem.num_bodies
    record: dict[str, Any] = {
        "workload": problem.workload,
        "dtype": problem.dtype,
        "num_bodies": N,
        "num_steps": T,
        "contenders": {},
    }
    if problem.workload == "W2":
        if preset.w2_check_bodies is None or preset.w2_check_bodies >= N:
            record["check"] = "every body at every step"
        else:
            record["check"] = (
                f"{len(check_bodies(N, preset.w2_check_bodies))} bodies spread over the batch at "
                f"every step, and every body at {len(check_steps(T))} steps"
            )
    runners: dict[str, tuple[Runner, int, int]] = {}
    for contender in CONTENDERS:
        if problem.workload not in contender.workloads:
            continue
        if contender.role == "reference" and not preset.reference:
            continue
        entry: dict[str, Any] = {"role": contender.role, "note": contender.note}
        record["contenders"][contender.name] = entry
        missing = _missing(contender.requires)
        if missing is not None:
            entry["skipped"] = f"`{missing}` is not installed (pip install 'jaxquat[bench]')"
            log(f"  {contender.name}: skipped, {entry['skipped']}")
            continue
        try:
            steps = T
            if contender.role == "peer" and (not contender.is_jax or N * T > 10**6):
                # A pilot on a few steps estimates the cost; slow peers are timed on fewer steps.
                # Two pilot lengths separate a NumPy peer's per-call set-up from its cost per
                # step, so a peer with an expensive set-up is not timed on too few steps (which
                # would understate its rate); the shorter pilot runs twice (the first call warms
                # up). A compiled JAX peer has no set-up beyond dispatch: one length, run twice.
                # NumPy pilots of 1 and 3 steps, and a timed call runs at least `long` steps: a
                # SciPy step at N = 10⁵ takes ~0.1 s, and 2 and 6 made the quick preset's SciPy
                # calls 0.66 s, three times its 0.2 s budget (~9 s more per run).
                short = min(T, 10 if contender.is_jax else 1)
                long = short if contender.is_jax else min(T, 3 * short)
                pilots = {}
                for pilot_steps in sorted({short, long}):
                    pilot = contender.make(problem, pilot_steps)
                    calls = 2 if pilot_steps == short else 1
                    pilots[pilot_steps] = min(_timed(pilot.run)[0] for _ in range(calls))
                    del pilot
                if long > short:
                    per_step = (pilots[long] - pilots[short]) / (long - short)
                    per_step = max(per_step, pilots[long] / long / 10)
                else:
                    per_step = pilots[short] / short
                setup = max(pilots[short] - short * per_step, 0.0)
                full = setup + T * per_step
                w2_full = problem.workload == "W2" and full <= (preset.w2_budget or 0.0)
                if full > preset.budget and not w2_full:
                    steps = min(T, max(long, int((preset.budget - setup) / per_step)))
            runner = contender.make(problem, steps)
            seconds, out = _timed(runner.run)
            error, norm_error = _check(problem, steps, out, preset.w2_check_bodies)
            del out
        except ImportError as e:
            entry["skipped"] = f"not available ({e})"
            log(f"  {contender.name}: skipped, {entry['skipped']}")
            continue
        except Exception as e:  # a contender that fails is reported, never hides the others
            entry["failed"] = f"{type(e).__name__}: {e}"
            log(f"  {contender.name}: FAILED, {entry['failed']}")
            continue
        entry.update(
            steps_timed=steps,
            compile_seconds=runner.compile_seconds,
            error=error,
            norm_error=norm_error,
            correct=bool(
                error <= ERROR_TOLERANCE[problem.dtype]
                and norm_error <= NORM_TOLERANCE[problem.dtype]
            ),
        )
        if not entry["correct"]:
            log(
                f"  {contender.name}: WRONG (error {error:.2e} rad, |q|-1 {norm_error:.1e}); not timed"
            )
            continue
        # Calls shorter than ~10 ms are repeated within one sample to beat the clock's resolution.
        number = max(1, min(1000, int(preset.sample_seconds / max(seconds, 1e-7))))
        runners[contender.name] = (runner, steps, number)
        entry["samples"] = []

    names = list(runners)
    # W2: every timed call follows an untimed call of the same contender, so its multi-gigabyte
    # output reuses memory freed a moment before. Otherwise a call that follows another contender's
    # samples is served memory the VM has handed back to the host (free page reporting), and pays
    # the host's page faults: seconds, at random, for whichever contender allocates after a pause.
    # Peers timed on fewer steps write a small trajectory and need no warm-up.
    warm_up = problem.workload == "W2"
    for round_index in range(preset.repeats):
        for name in names if round_index % 2 == 0 else reversed(names):
            runner, steps, number = runners[name]
            if warm_up and steps == T:
                _block(runner.run())
            start = time.perf_counter()
            for _ in range(number):
                out = _block(runner.run())
                del out
            record["contenders"][name]["samples"].append((time.perf_counter() - start) / number)

    for name in names:
        entry = record["contenders"][name]
        entry["seconds"] = statistics.median(entry["samples"])
        entry["rate"] = N * entry["steps_timed"] / entry["seconds"]
    _rank(record)
    return record


def _rank(record: dict) -> None:
    """Add the best peer of a row and every contender's ratio to it."""
    contenders = record["contenders"]
    peers = {n: e for n, e in contenders.items() if e["role"] == "peer" and "rate" in e}
    if not peers:
        record["best_peer"] = None
        return
    best = max(peers, key=lambda n: peers[n]["rate"])
    record["best_peer"] = best
    for entry in contenders.values():
        if "rate" in entry:
            entry["ratio_to_best_peer"] = entry["rate"] / peers[best]["rate"]


# ----------------------------------------------------------------------------------------------------
# W4: coning, work–precision

# q(t) = exp(a t) ⊗ exp(b t) ⊗ q₀ with a along z (precession) and b tilted (spin): in the world frame
# ω(t) = a + R(exp(a t)) b, a vector sweeping a cone about z. Final time: a non-integer number of turns.
CONING_PRECESSION = (0.0, 0.0, 1.7)
CONING_SPIN = (2.5 * math.sin(0.6), 0.0, 2.5 * math.cos(0.6))
CONING_INITIAL = (0.9, 0.1, -0.3, 0.2)
CONING_END = 6.3


def coning_omega(t, xp=np):
    """World-frame ω(t) = a + R(exp(a t)) b of the coning motion."""
    a = xp.asarray(CONING_PRECESSION, dtype=xp.float64)
    b = xp.asarray(CONING_SPIN, dtype=xp.float64)
    return a + _q_rotate(_q_exp(a * t, xp), b, xp)


def coning_omega_scalar(t: float) -> np.ndarray:
    """`coning_omega` for one time as plain NumPy arithmetic, for numpy-quaternion's integrator,
    which calls ω once per stage from Python: the generic `xp` helpers above cost 36 µs a call there
    (0.8 µs for this), and that, not the integrator, was most of the peer's W4 time."""
    precession = CONING_PRECESSION[2]  # a is along z: R(exp(a t)) turns about z by |a| t
    bx, by, bz = CONING_SPIN
    c, s = math.cos(precession * t), math.sin(precession * t)
    return np.array([c * bx - s * by, s * bx + c * by, precession + bz])


def coning_exact(t) -> np.ndarray:
    """The closed-form orientation of the coning motion at time t (float64 `(4,)`)."""
    q0 = np.asarray(CONING_INITIAL) / np.linalg.norm(CONING_INITIAL)
    a = np.asarray(CONING_PRECESSION)
    b = np.asarray(CONING_SPIN)
    return _q_mul(_q_mul(_q_exp(a * t, np), _q_exp(b * t, np), np), q0, np)


def _autorange(
    function: Callable[[], Any],
    repeats: int,
    sample_seconds: float = 0.02,
    first_seconds: float | None = None,
) -> float:
    """Median seconds per call, repeating short calls within each sample. The first call (also the
    warm-up) sizes the samples; `first_seconds`: such a call was just made and took this long."""
    seconds = _timed(function)[0] if first_seconds is None else first_seconds
    number = max(1, min(10000, int(sample_seconds / max(seconds, 1e-7))))
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(number):
            _block(function())
        samples.append((time.perf_counter() - start) / number)
    return statistics.median(samples)


def _w4_series(preset: Preset, log: Callable[[str], None]) -> list[dict]:
    import jax
    import jax.numpy as jnp

    t_end = CONING_END
    exact = coning_exact(t_end)
    q0 = jnp.asarray(coning_exact(0.0))
    series: list[dict] = []

    def add(name, role, points, note="", **extra):
        series.append({"name": name, "role": role, "points": points, "note": note, **extra})
        if points:
            best = min(p["error"] for p in points)
            log(f"  {name}: {len(points)} points, best error {best:.1e}")

    def omega(t, q=None):
        return coning_omega(t, jnp)

    def swept(name, default):
        return tuple(dict(preset.w4_sweeps).get(name, default))

    # jaxquat's fixed-step integrators.
    try:
        integrate, _ = _load_integrate()
    except ImportError as e:
        log(f"  jaxquat integrate: skipped ({e})")
        integrate = None
    if integrate is not None:
        for method in preset.w4_methods:
            points, compile_seconds = [], 0.0
            try:
                for steps in swept(f"jaxquat integrate {method}", preset.w4_steps):
                    steps = int(steps)
                    runner = _compiled(
                        lambda q0, steps=steps, method=method: integrate(
                            q0, omega, t_end / steps, steps, method=method, save="final"
                        ),
                        q0,
                    )
                    compile_seconds += runner.compile_seconds or 0.0
                    error = float(angle_error(runner.run(), exact))
                    seconds = _autorange(runner.run, preset.w4_repeats, 2 * preset.sample_seconds)
                    points.append({"steps": steps, "error": error, "seconds": seconds})
            except Exception as e:
                log(f"  jaxquat integrate {method}: FAILED {type(e).__name__}: {e}")
            add(f"jaxquat integrate {method}", "jaxquat", points, compile_seconds=compile_seconds)

    # diffrax: jaxquat's solvers and stock Tsit5.
    if _missing(("diffrax",)) is None:
        import diffrax

        def solve(term, solver, controller_of, dt0_of):
            def function(y0, parameter):
                solution = diffrax.diffeqsolve(
                    term,
                    solver,
                    0.0,
                    t_end,
                    dt0_of(parameter),
                    y0,
                    stepsize_controller=controller_of(parameter),
                    saveat=diffrax.SaveAt(t1=True),
                    max_steps=2**17,
                )
                return solution.ys[-1], solution.stats["num_steps"]

            return function

        def sweep(name, role, function, parameters, kind, note=""):
            points = []
            try:
                start = time.perf_counter()
                compiled = jax.jit(function).lower(q0, jnp.asarray(parameters[0])).compile()
                compile_seconds = time.perf_counter() - start
                for parameter in parameters:
                    p = jnp.asarray(parameter)
                    y, steps = compiled(q0, p)
                    seconds = _autorange(
                        lambda p=p: compiled(q0, p), preset.w4_repeats, 2 * preset.sample_seconds
                    )
                    points.append(
                        {
                            kind: parameter,
                            "steps": int(steps),
                            "error": float(angle_error(y, exact)),
                            "seconds": seconds,
                        }
                    )
            except Exception as e:
                log(f"  {name}: FAILED {type(e).__name__}: {e}")
                compile_seconds = None
            add(name, role, points, note=note, compile_seconds=compile_seconds)

        def plain_rate(t, y, args):
            w = coning_omega(t, jnp)
            return 0.5 * _q_mul(jnp.concatenate([jnp.zeros_like(w[:1]), w]), y, jnp)

        def adaptive(tolerance):
            return diffrax.PIDController(rtol=tolerance, atol=tolerance)

        sweep(
            "diffrax Tsit5 (stock)",
            "peer",
            solve(diffrax.ODETerm(plain_rate), diffrax.Tsit5(), adaptive, lambda p: None),
            list(swept("diffrax Tsit5 (stock)", preset.w4_tolerances)),
            "tolerance",
            note="adaptive, rtol = atol = tolerance, plain rate ½ ω̃ q in ℝ⁴",
        )
        try:
            from . import _solvers
        except ImportError as e:
            log(f"  jaxquat diffrax solvers: skipped ({e})")
            _solvers = None
        if _solvers is not None:
            term = diffrax.ODETerm(_solvers.kinematic_vector_field(omega))
            fixed = diffrax.ConstantStepSize()
            for solver_name in [n for n in preset.w4_solvers if n != "RKMK45"]:
                solver_class = getattr(_solvers, solver_name, None)
                if solver_class is None:
                    log(f"  jaxquat diffrax {solver_name}: not available")
                    continue
                name = f"jaxquat diffrax {solver_name}"
                sweep(
                    name,
                    "jaxquat",
                    solve(term, solver_class(), lambda p: fixed, lambda p: p),
                    [t_end / steps for steps in swept(name, preset.w4_steps)],
                    "dt",
                )
            if "RKMK45" in preset.w4_solvers and hasattr(_solvers, "RKMK45"):
                sweep(
                    "jaxquat diffrax RKMK45",
                    "jaxquat",
                    solve(term, _solvers.RKMK45(), adaptive, lambda p: None),
                    list(swept("jaxquat diffrax RKMK45", preset.w4_tolerances)),
                    "tolerance",
                    note="adaptive, rtol = atol = tolerance",
                )
    else:
        log("  diffrax: skipped (not installed)")

    # numpy-quaternion's integrate_angular_velocity (scipy's DOP853, adaptive).
    if _missing(("quaternion", "scipy")) is None:
        import quaternion

        points = []
        start_orientation = quaternion.from_float_array(coning_exact(0.0))
        name = "numpy-quaternion integrate_angular_velocity"
        for tolerance in swept(name, preset.w4_tolerances):

            def run(tolerance=tolerance):
                # integrate_angular_velocity resets the global warning filters; contain that.
                with warnings.catch_warnings():
                    return quaternion.integrate_angular_velocity(
                        coning_omega_scalar,
                        0.0,
                        t_end,
                        R0=start_orientation,
                        tolerance=tolerance,
                    )

            times, orientations = run()
            final = quaternion.as_float_array(orientations[-1])
            points.append(
                {
                    "tolerance": tolerance,
                    "steps": len(times) - 1,
                    "error": float(angle_error(final, coning_exact(times[-1]))),
                    "seconds": _autorange(
                        run, max(1, min(preset.w4_repeats, 3)), 2 * preset.sample_seconds
                    ),
                }
            )
        add(
            name,
            "peer",
            points,
            note="SciPy DOP853, atol = tolerance, rtol = 0",
        )
    else:
        log("  numpy-quaternion: skipped (not installed)")
    return series


def time_at_error(points: Sequence[dict], target: float) -> tuple[float | None, str]:
    """Seconds a method needs to reach `target` final error, from its work–precision points.

    Interpolates log(time) linearly in log(error) along the Pareto front (points that are more
    accurate than every cheaper point). Returns (seconds, how): how is "interpolated", "at most"
    (already the cheapest point beats the target), or "not reached".
    """
    front = []
    for point in sorted(points, key=lambda p: p["seconds"]):
        if not front or point["error"] < front[-1]["error"]:
            front.append(point)
    if not front or front[-1]["error"] > target:
        return None, "not reached"
    if front[0]["error"] <= target:
        return front[0]["seconds"], "at most"
    for cheap, dear in zip(front, front[1:], strict=False):
        if dear["error"] <= target:  # the first such pair brackets the target (front errors fall)
            if dear["error"] <= 0.0:
                return dear["seconds"], "at most"
            fraction = math.log(cheap["error"] / target) / math.log(cheap["error"] / dear["error"])
            log_seconds = math.log(cheap["seconds"]) + fraction * math.log(
                dear["seconds"] / cheap["seconds"]
            )
            return math.exp(log_seconds), "interpolated"
    return None, "not reached"


# (the peer's time at target is an upper bound, jaxquat's is) → what the speed-up is.
_SPEEDUP_BOUND = {
    (False, False): "exact",
    (True, False): "at most",
    (False, True): "at least",
    (True, True): "unknown",
}


def run_w4(preset: Preset, output: Path, log: Callable[[str], None]) -> dict:
    series = _w4_series(preset, log)
    for entry in series:
        seconds, how = time_at_error(entry["points"], W4_TARGET_ERROR)
        entry["seconds_at_target"] = seconds
        entry["at_target"] = how
    record: dict[str, Any] = {
        "target_error": W4_TARGET_ERROR,
        "t_end": CONING_END,
        "series": series,
    }
    best_jaxquat = _best_at_target(series, "jaxquat")
    record["best_jaxquat"] = best_jaxquat
    record["speedups"] = {}
    # A time "at most" (the cheapest point already beats the target) is an upper bound, so is a
    # speed-up from a peer's such time; one from jaxquat's is a lower bound; from both, neither.
    record["speedup_bounds"] = {}
    if best_jaxquat is not None:
        best = next(s for s in series if s["name"] == best_jaxquat)
        for entry in series:
            if entry["role"] == "peer" and entry["seconds_at_target"] is not None:
                name = entry["name"]
                record["speedups"][name] = entry["seconds_at_target"] / best["seconds_at_target"]
                bounds = (entry["at_target"] == "at most", best["at_target"] == "at most")
                record["speedup_bounds"][name] = _SPEEDUP_BOUND[bounds]
    png = output / "w4_work_precision.png"
    try:
        _plot_w4(series, png)
        record["png"] = png.name
    except Exception as e:  # the table and JSON matter more than the picture
        log(f"  W4 plot failed: {type(e).__name__}: {e}")
    return record


def _best_at_target(series: Sequence[dict], role: str) -> str | None:
    candidates = [s for s in series if s["role"] == role and s["seconds_at_target"] is not None]
    if not candidates:
        return None
    return min(candidates, key=lambda s: s["seconds_at_target"])["name"]


def _plot_w4(series: Sequence[dict], path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(8, 5.5))
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    # More series than the default 10-colour cycle: euler and RKMK45 (and midpoint and numpy-quaternion)
    # came out in the same colour; tab20 gives every series its own.
    from matplotlib import colormaps

    colours = colormaps["tab20"].colors
    for index, entry in enumerate(series):
        # In order of work (steps up, tolerance down), not of measured time: a noisy time reordered
        # a method's points and drew its curve as a zig-zag.
        points = sorted(
            entry["points"], key=lambda p: (-p["tolerance"],) if "tolerance" in p else (p["steps"],)
        )
        if not points:
            continue
        floor = 1e-17  # exact-to-round-off points still appear on a log axis
        axes.loglog(
            [p["seconds"] for p in points],
            [max(p["error"], floor) for p in points],
            marker="o" if entry["role"] == "jaxquat" else "s",
            linestyle="-" if entry["role"] == "jaxquat" else "--",
            markersize=3.5,
            color=colours[index % len(colours)],
            label=entry["name"],
        )
    axes.axhline(W4_TARGET_ERROR, color="grey", linewidth=0.8, linestyle=":")
    axes.set_xlabel("wall time per solve (s)")
    axes.set_ylabel("final orientation error (rad)")
    axes.set_title("W4: coning, work–precision (float64, one body)")
    axes.grid(True, which="major", linewidth=0.3)
    axes.legend(fontsize=7, loc="best")
    figure.tight_layout()
    figure.savefig(path, dpi=120)


# ----------------------------------------------------------------------------------------------------
# W5: gradients


def _w5_forwards(problem: Problem, sampled: bool) -> dict[str, Callable]:
    """Final orientations as functions of (q0, ω) for the differentiable contenders."""
    import jax
    import jax.numpy as jnp
    from jax import lax

    dt, T = problem.dt, problem.num_steps
    functions: dict[str, Callable] = {}
    try:
        integrate, make_sampled = _load_integrate()

        def jaxquat_final(q0, omega):
            source = make_sampled(omega, dt) if sampled else omega
            return integrate(q0, source, dt, T, save="final")

        functions["jaxquat"] = jaxquat_final
    except ImportError:
        pass

    def scan_final(advance):
        def final(q0, omega):
            if sampled:
                return lax.scan(lambda q, w: (advance(q, w), None), q0, omega)[0]
            return lax.scan(lambda q, _: (advance(q, omega), None), q0, None, length=T)[0]

        return final

    functions["JAX loop"] = scan_final(lambda q, w: _q_mul(_q_exp(w * dt, jnp), q, jnp))
    if _missing(("jaxlie",)) is None:
        import jaxlie

        functions["jaxlie"] = scan_final(
            jax.vmap(lambda q, w: (jaxlie.SO3.exp(w * dt) @ jaxlie.SO3(q)).wxyz)
        )
    return functions


def run_w5_row(problem: Problem, sampled: bool, preset: Preset, log: Callable[[str], None]) -> dict:
    """Forward loss and `jax.grad` w.r.t. all ω for each differentiable contender; ratio grad/forward."""
    import jax
    import jax.numpy as jnp

    q0 = jnp.asarray(problem.q0)
    omega = problem.omegas if sampled else jnp.asarray(problem.omega)
    rng = np.random.default_rng(7)
    target = rng.normal(size=problem.q0.shape)
    target = jnp.asarray(target / np.linalg.norm(target, axis=-1, keepdims=True), dtype=q0.dtype)
    record: dict[str, Any] = {
        "variant": "sampled ω (T, N, 3)" if sampled else "constant ω (N, 3)",
        "dtype": problem.dtype,
        "num_bodies": problem.num_bodies,
        "num_steps": problem.num_steps,
        "contenders": {},
    }
    forwards = _w5_forwards(problem, sampled)
    peers_max = preset.w5_peers_max_bodies
    subset = None  # compare the gradient on these bodies only (all when None)
    if peers_max is not None and problem.num_bodies > peers_max:
        subset = check_bodies(problem.num_bodies, peers_max)
        record["checked_bodies"] = len(subset)
        log(f"  peers not timed above N = {peers_max:,}; gradient checked on {len(subset)} bodies")

    # q0 and target are arguments, as in W1–W3: closed over, they were baked into the executable as
    # constants and XLA folded the work on them alone (e.g. a `where` on q0) out of the timed call.
    def gradient_of(final) -> Runner:
        return _compiled(
            lambda w, q0, target: jax.grad(lambda v: _loss(final(q0, v), target, jnp))(w),
            omega,
            q0,
            target,
        )

    def rows(g):  # the gradient's rows of the checked bodies (the body axis is ω's second-last)
        return g if subset is None else np.take(g, subset, axis=-2)

    # Reference gradient: the independent hand-written loop in float64 (itself checked against the
    # closed form's gradient for constant ω in tests/test_bench.py). In a full float64 row that is the
    # JAX loop contender's own gradient, compiled once for both.
    loop_gradient = None
    reference_forward = forwards["JAX loop"]
    if problem.dtype == "float64" and subset is None:
        loop_gradient = gradient_of(reference_forward)
        reference = np.asarray(_block(loop_gradient.run()))
    else:
        pick = (lambda a: a) if subset is None else (lambda a: jnp.take(a, subset, axis=-2))
        q0_64, omega_64, target_64 = (pick(a).astype(jnp.float64) for a in (q0, omega, target))
        reference = jax.jit(jax.grad(lambda w: _loss(reference_forward(q0_64, w), target_64, jnp)))(
            omega_64
        )
        reference = np.asarray(reference)
        del omega_64
    reference_norm = float(np.linalg.norm(reference))
    if subset is not None:
        forwards = {k: v for k, v in forwards.items() if k == "jaxquat"}

    for name, final in forwards.items():
        entry: dict[str, Any] = {"role": "jaxquat" if name == "jaxquat" else "peer"}
        record["contenders"][name] = entry
        try:
            forward = _compiled(
                lambda w, q0, target, final=final: _loss(final(q0, w), target, jnp),
                omega,
                q0,
                target,
            )
            if name == "JAX loop" and loop_gradient is not None:
                gradient = loop_gradient
            else:
                gradient = gradient_of(final)
            gradient_first, g = _timed(gradient.run)  # the check's call is also the warm-up
            g = rows(np.asarray(g))
            error = float(np.linalg.norm(g.astype(np.float64) - reference)) / max(
                reference_norm, 1e-300
            )
            # float32: measured 5e-7 (jaxquat) to 7e-6 (the JAX loop, jaxlie); a gradient missing
            # one step is 3e-2 off, which 2e-2 let through with a margin of only 1.5×.
            tolerance = 1e-6 if problem.dtype == "float64" else 1e-3
            entry.update(
                compile_seconds=(forward.compile_seconds or 0.0)
                + (gradient.compile_seconds or 0.0),
                gradient_error=error,
                correct=bool(error <= tolerance),
            )
            del g
            if not entry["correct"]:
                log(f"  {name}: WRONG gradient (relative error {error:.1e}); not timed")
                continue
            entry["forward_seconds"] = _autorange(
                forward.run, preset.repeats, preset.sample_seconds
            )
            # Warmed up again right before its samples (the check's call came before the forward's
            # timing): the gradient writes a fresh T × N × 3 array per call, and on a virtual machine
            # memory left idle for a moment can stall its first touch for seconds (measured at
            # N = 10⁵: 3.9 s and 2.1 s for a first call, then 1.05 s).
            _block(gradient.run())
            entry["gradient_seconds"] = _autorange(
                gradient.run, preset.repeats, preset.sample_seconds, gradient_first
            )
            entry["ratio"] = entry["gradient_seconds"] / entry["forward_seconds"]
        except Exception as e:
            entry["failed"] = f"{type(e).__name__}: {e}"
            log(f"  {name}: FAILED, {entry['failed']}")
    peers = [
        e for e in record["contenders"].values() if e["role"] == "peer" and "gradient_seconds" in e
    ]
    if peers:
        best = min(e["gradient_seconds"] for e in peers)
        for entry in record["contenders"].values():
            if "gradient_seconds" in entry:
                entry["gradient_vs_best_peer"] = best / entry["gradient_seconds"]
    return record


# ----------------------------------------------------------------------------------------------------
# Machine, report


def describe_machine() -> dict:
    """CPU, cores, memory, load and library versions, for the record."""
    import importlib.metadata

    model = platform.processor() or "unknown"
    flags = ""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name") and model in ("unknown", "x86_64", ""):
                    model = line.split(":", 1)[1].strip()
                elif line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                if line.startswith("flags") and not flags:
                    flags = line
    except OSError:
        pass
    memory = None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemTotal"):
                    memory = f"{int(line.split()[1]) / 2**20:.0f} GiB"
    except OSError:
        pass
    versions = {}
    for package in (
        "jax",
        "jaxlib",
        "numpy",
        "scipy",
        "numpy-quaternion",
        "jaxlie",
        "diffrax",
        "jaxquat",
    ):
        try:
            versions[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            versions[package] = None
    vector = [f for f in ("avx512f", "avx2") if f" {f} " in flags]
    try:
        load = os.getloadavg()
    except OSError:
        load = None
    return {
        "cpu": model,
        "cores": os.cpu_count(),
        "vector_extensions": vector,
        "memory": memory,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "versions": versions,
        "load_average_at_start": load,
        "huge_pages": huge_pages_status(),
        "date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
    }


def _rate(x: float) -> str:
    for scale, suffix in ((1e9, " G"), (1e6, " M"), (1e3, " k")):
        if x >= scale:
            return f"{x / scale:.3g}{suffix}"
    return f"{x:.3g}"


def _seconds(x: float | None) -> str:
    if x is None:
        return "—"
    if x >= 1:
        return f"{x:.2f} s"
    if x >= 1e-3:
        return f"{x * 1e3:.3g} ms"
    return f"{x * 1e6:.3g} µs"


def _cell(entry: dict | None, record: dict) -> str:
    if entry is None:
        return "—"
    if "skipped" in entry:
        return "not installed" if "installed" in entry["skipped"] else "n/a"
    if "failed" in entry:
        return "failed"
    if not entry.get("correct", False):
        return "WRONG"
    text = _rate(entry["rate"])
    if entry["steps_timed"] != record["num_steps"]:
        text += "†"
    if "ratio_to_best_peer" in entry:
        text += f" ({entry['ratio_to_best_peer']:.2f}×)"
    return text


def render_markdown(report: dict) -> str:
    machine = report["machine"]
    versions = ", ".join(f"{k} {v}" for k, v in machine["versions"].items() if v)
    lines = [
        f"# jaxquat benchmarks — preset `{report['preset']}`",
        "",
        f"Machine: {machine['cpu']}, {machine['cores']} cores"
        + (f" ({', '.join(machine['vector_extensions'])})" if machine["vector_extensions"] else "")
        + f", {machine['memory']} RAM; {machine['platform']}; Python {machine['python']}; {versions}.",
        f"Run {machine['date_utc']}, {report['elapsed_seconds']:.0f} s; load average at start "
        f"{_load(machine['load_average_at_start'])}, at end {_load(report.get('load_average_at_end'))}.",
        f"Large buffers: {machine.get('huge_pages', 'unknown')}.",
        "",
    ]
    rows = report["rows"]
    if rows:
        names: list[str] = []
        for row in rows:
            for name in row["contenders"]:
                if name not in names:
                    names.append(name)
        lines += [
            "## W1–W3: body-steps per second (ratio to the best peer of the row)",
            "",
            f"T = {rows[0]['num_steps']} steps of Δt = {DT} s; medians of {report['config']['repeats']}"
            " interleaved runs, compiled ahead of time.",
            "",
            "| workload | dtype | N | "
            + " | ".join(names)
            + " | jaxquat ÷ best peer | best peer |",
            "|---|---|---:|" + "---:|" * len(names) + "---:|---|",
        ]
        for row in rows:
            jaxquat = row["contenders"].get("jaxquat", {})
            ratio = jaxquat.get("ratio_to_best_peer")
            lines.append(
                f"| {row['workload']} | {row['dtype']} | {row['num_bodies']:,} | "
                + " | ".join(_cell(row["contenders"].get(n), row) for n in names)
                + f" | {f'**{ratio:.2f}×**' if ratio else '—'} | {row.get('best_peer') or '—'} |"
            )
        lines += [
            "",
            "† timed on fewer steps to stay within the per-call budget (cost per step is constant; in W2 "
            "the peers that fit a larger budget run all T steps, as a smaller trajectory is cheaper "
            "per step on a virtual machine).",
            "",
        ]
        checks = [
            f"{row['workload']} {row['dtype']} N = {row['num_bodies']:,}: checked against the closed "
            f"form on {row['check']} (the same for every contender)."
            for row in rows
            if "check" in row and not row["check"].startswith("every body")
        ]
        lines += checks + ([""] if checks else [])
        lines += [
            "Compile time (s) of the JAX contenders, per row:",
            "",
            "| workload | dtype | N | " + " | ".join(names) + " |",
            "|---|---|---:|" + "---:|" * len(names),
        ]
        for row in rows:
            cells = []
            for n in names:
                entry = row["contenders"].get(n)
                seconds = entry.get("compile_seconds") if entry else None
                cells.append(f"{seconds:.2f}" if seconds is not None else "—")
            lines.append(
                f"| {row['workload']} | {row['dtype']} | {row['num_bodies']:,} | "
                + " | ".join(cells)
                + " |"
            )
        lines.append("")
        notes = {}
        for row in rows:
            for name, entry in row["contenders"].items():
                if entry.get("note"):
                    notes[name] = entry["note"]
        if notes:
            lines += ["Contenders:", ""] + [f"- **{n}**: {t}" for n, t in notes.items()] + [""]
    w4 = report.get("w4")
    if w4:
        lines += [
            f"## W4: coning work–precision (float64, one body, t = 0 … {w4['t_end']} s)",
            "",
            f"Time to reach a final error of {w4['target_error']:.0e} rad (log–log interpolation on "
            "each method's Pareto front)" + (f"; plot: `{w4['png']}`." if w4.get("png") else "."),
            "",
            "| method | role | time at target | best error reached | points |",
            "|---|---|---:|---:|---:|",
        ]
        for entry in sorted(
            w4["series"],
            key=lambda s: (s["seconds_at_target"] is None, s["seconds_at_target"] or 0),
        ):
            best_error = min((p["error"] for p in entry["points"]), default=None)
            at = entry["seconds_at_target"]
            text = (
                "not reached"
                if at is None
                else ("≤ " if entry["at_target"] == "at most" else "") + _seconds(at)
            )
            lines.append(
                f"| {entry['name']} | {entry['role']} | {text} | "
                f"{f'{best_error:.1e}' if best_error is not None else '—'} | {len(entry['points'])} |"
            )
        if w4.get("best_jaxquat"):
            marks = {"at most": "≤ ", "at least": "≥ ", "unknown": "~"}
            bounds = w4.get("speedup_bounds", {})
            speedups = ", ".join(
                f"{n} {marks.get(bounds.get(n, 'exact'), '')}{s:.1f}×"
                for n, s in w4["speedups"].items()
            )
            lines += [
                "",
                f"Best jaxquat method: {w4['best_jaxquat']}; its speed-up over {speedups}.",
            ]
            if any(b != "exact" for b in bounds.values()):
                lines.append(
                    "(≤ / ≥: a speed-up from a time at target that is only an upper bound, the "
                    "peer's / jaxquat's; ~: both are.)"
                )
        lines.append("")
    w5 = report.get("w5", [])
    if w5:
        lines += [
            "## W5: `jax.grad` of a final-orientation loss w.r.t. all ω",
            "",
            "| ω | dtype | N | contender | forward | gradient | gradient ÷ forward | gradient speed vs best peer |",
            "|---|---|---:|---|---:|---:|---:|---:|",
        ]
        for row in w5:
            for name, entry in row["contenders"].items():
                if "gradient_seconds" in entry:
                    versus = entry.get("gradient_vs_best_peer")
                    cells = (
                        f"{_seconds(entry['forward_seconds'])} | {_seconds(entry['gradient_seconds'])} | "
                        f"{entry['ratio']:.2f} | {'—' if versus is None else f'{versus:.2f}×'}"
                    )
                else:
                    cells = "failed | | | " if "failed" in entry else "WRONG | | | "
                lines.append(
                    f"| {row['variant']} | {row['dtype']} | {row['num_bodies']:,} | {name} | {cells} |"
                )
        subsets = sorted(
            {(r["num_bodies"], r["checked_bodies"]) for r in w5 if "checked_bodies" in r}
        )
        for size, count in subsets:
            lines += [
                "",
                f"At N = {size:,} only jaxquat is timed (a peer's gradient there takes many seconds); "
                f"its gradient is checked on {count} bodies spread over the batch against the "
                "hand-written loop's.",
            ]
        lines.append("")
    if report.get("notes"):
        lines += ["## Notes", ""] + [f"- {n}" for n in report["notes"]] + [""]
    return "\n".join(lines)


def _load(load) -> str:
    return "?" if not load else " / ".join(f"{x:.2f}" for x in load)


def _json_default(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    return str(x)


def to_json(report: dict) -> str:
    """The report as strict JSON: a non-finite number (the error of a contender that returned NaN,
    say) is written as null, since NaN and Infinity are not JSON and strict readers refuse them."""

    def finite(x):
        if isinstance(x, dict):
            return {k: finite(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [finite(v) for v in x]
        if isinstance(x, (float, np.floating)) and not math.isfinite(x):
            return None
        return x

    return json.dumps(finite(report), indent=1, default=_json_default, allow_nan=False)


# ----------------------------------------------------------------------------------------------------
# Entry point


class _ArgumentError(Exception):
    """A bad `jaxquat bench` argument: reported by `main` in one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    """An `ArgumentParser` whose errors are one-line `_ArgumentError`s, not a usage dump + exit, and
    whose options that take a value may be given only once (as in `jaxquat`'s own parser)."""

    def error(self, message: str):  # noqa: D102 (argparse's signature)
        raise _ArgumentError(message)

    def add_argument(self, *names, **kwargs):  # noqa: D102 (argparse's signature)
        if names and names[0].startswith("-") and "action" not in kwargs:
            from ._cli import _Once

            kwargs["action"] = _Once
        return super().add_argument(*names, **kwargs)


# Counts above this (an int32 index) fail inside the run (`--steps 10**23`: an OverflowError,
# reported as a failed row) instead of at the option.
_MAX_COUNT = 2**31 - 1


def _positive_int(text: str) -> int:
    if not re.fullmatch(r"\+?[0-9]+", text.strip()) or not 1 <= int(text) <= _MAX_COUNT:
        raise argparse.ArgumentTypeError(
            f"must be a positive integer up to {_MAX_COUNT:,}, got {text!r}"
        )
    return int(text)


def _positive_ints(text: str) -> tuple[int, ...]:
    try:
        values = tuple(_positive_int(part) for part in text.split(","))
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"must be comma-separated positive integers up to {_MAX_COUNT:,}, got {text!r}"
        ) from None
    if len(set(values)) < len(values):  # every row would run, and be reported, twice
        raise argparse.ArgumentTypeError(f"lists a value twice: {text!r}")
    return values


def _directory(text: str) -> Path:
    if not text.strip():  # Path("") is ".": the results went to the working directory
        raise argparse.ArgumentTypeError("must name a directory, got ''")
    return Path(text)


def _positive_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number of seconds, got {text!r}")
    return value


def _parse(argv: list[str] | None) -> argparse.Namespace:
    parser = _Parser(
        prog="jaxquat bench",
        description="Benchmark jaxquat's integrators against SciPy, numpy-quaternion, jaxlie and plain JAX.",
    )
    parser.add_argument("--preset", choices=sorted(PRESETS), default="quick", help="default: quick")
    parser.add_argument(
        "--output",
        type=_directory,
        default=Path("benchmarks/results"),
        help="directory for results.md, "
        "results.json and w4_work_precision.png (default: benchmarks/results)",
    )
    parser.add_argument("--workloads", help="comma-separated subset of W1,W2,W3,W4,W5")
    parser.add_argument(
        "--sizes", type=_positive_ints, help="comma-separated numbers of bodies (W1–W3, W5)"
    )
    parser.add_argument("--dtypes", help="comma-separated: float64,float32")
    parser.add_argument("--steps", type=_positive_int, help="number of steps T")
    parser.add_argument("--repeats", type=_positive_int, help="timing rounds per row")
    parser.add_argument(
        "--w5-sizes", type=_positive_ints, help="comma-separated numbers of bodies for W5"
    )
    parser.add_argument(
        "--budget",
        type=_positive_seconds,
        help="seconds one peer call may take before it runs fewer steps (W2 included)",
    )
    parser.add_argument("--quiet", action="store_true", help="print only the final table")
    parser.add_argument(
        "--no-huge-pages",
        action="store_true",
        help="do not relaunch with glibc's huge-page tunable (python -m jaxquat bench and "
        "benchmarks/run.py relaunch with it by default, for every contender)",
    )
    return parser.parse_args(argv)


def _settings(argv: list[str] | None) -> tuple[argparse.Namespace, Preset]:
    """The parsed arguments and the preset they ask for. Raises `_ArgumentError` (or SystemExit, for
    --help) from the parser and ValueError for the checks that need the parsed values."""
    args = _parse(argv)
    changes: dict[str, Any] = {}
    if args.workloads is not None:
        workloads = tuple(w.strip().upper() for w in args.workloads.split(","))
        if "" in workloads:  # `--workloads ""` ran the whole preset
            raise ValueError(
                f"--workloads must be a comma-separated list of W1..W5, got {args.workloads!r}"
            )
        if len(set(workloads)) < len(workloads):
            raise ValueError(f"--workloads lists a workload twice: {args.workloads!r}")
        unknown = [w for w in workloads if w not in ("W1", "W2", "W3", "W4", "W5")]
        if unknown:
            raise ValueError(
                f"--workloads: unknown workload(s) {', '.join(unknown)}; expected W1..W5"
            )
        changes["workloads"] = workloads
    if args.sizes:
        changes["sizes"] = args.sizes
        changes["w5_sizes"] = changes["sizes"]
    if args.dtypes is not None:
        dtypes = tuple(d.strip() for d in args.dtypes.split(","))
        if any(d not in ("float64", "float32") for d in dtypes):  # "" included: not ignored
            raise ValueError(f"--dtypes must be float64 and/or float32; got {args.dtypes!r}")
        if len(set(dtypes)) < len(dtypes):
            raise ValueError(f"--dtypes lists a dtype twice: {args.dtypes!r}")
        changes["dtypes"] = dtypes
    if args.w5_sizes:
        changes["w5_sizes"] = args.w5_sizes
    if args.budget is not None:
        changes["budget"] = args.budget
        changes["w2_budget"] = None  # the user's budget holds for W2 too
    if args.steps is not None:
        changes["num_steps"] = args.steps
    if args.repeats is not None:
        changes["repeats"] = args.repeats
    if args.output.exists() and not args.output.is_dir():
        raise ValueError(f"--output {args.output}: exists and is not a directory")
    _check_creatable(args.output)
    return args, dataclasses.replace(PRESETS[args.preset], **changes)


def _check_creatable(directory: Path) -> None:
    """A `ValueError` when `directory` (absent) plainly cannot be made: its nearest existing
    ancestor is a file, or one this user may not write into. Nothing is created here (`main` makes
    it, and reports what else the system refuses)."""
    ancestor = directory.absolute()
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if ancestor == directory.absolute():
        return
    if not ancestor.is_dir():
        raise ValueError(f"--output {directory}: {ancestor} is not a directory")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise ValueError(f"--output {directory}: no permission to create it in {ancestor}")


def will_run(argv: list[str]) -> bool:
    """Whether `main(argv)` gets past its argument checks: False for --help or arguments it rejects,
    which `main` prints without JAX's backend (the command line starts the backend only when True).
    A directory `--output` that cannot be created for a reason `_check_creatable` does not foresee
    is found later, by `main`."""
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            _settings(argv)
    except (_ArgumentError, SystemExit, ValueError):
        return False
    return True


def main(argv: list[str] | None = None) -> int:
    """Run the suite; write results.md, results.json and the W4 PNG into `--output`.

    Returns 0 on success, 1 if a jaxquat contender gave a wrong answer, 2 on bad arguments.
    """
    try:
        args, preset = _settings(argv)
    except _ArgumentError as e:
        print(f"jaxquat bench: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    except SystemExit as e:  # --help
        return int(e.code or 0) if e.code in (0, None) else 2
    except ValueError as e:
        print(f"jaxquat bench: error: {e}", file=sys.stderr)
        return 2

    import jax

    # float64 rows need x64; float32 rows cast explicitly, so turning it on changes nothing for them.
    jax.config.update("jax_enable_x64", True)

    def log(message: str) -> None:
        if not args.quiet:
            print(message, flush=True)

    output: Path = args.output
    try:
        output.mkdir(parents=True, exist_ok=True)
    except OSError as e:  # a file on the way (a/b with a a file), no permission, ...
        print(f"jaxquat bench: error: --output {output}: {e.strerror or e}", file=sys.stderr)
        return 2
    started = time.perf_counter()
    report: dict[str, Any] = {
        "preset": args.preset,
        "config": dataclasses.asdict(preset),
        "machine": describe_machine(),
        "rows": [],
        "w5": [],
        "notes": [],
    }
    for module, package in (
        ("scipy", "scipy"),
        ("quaternion", "numpy-quaternion"),
        ("jaxlie", "jaxlie"),
    ):
        if _missing((module,)):
            report["notes"].append(f"{package} is not installed: its columns are skipped.")
    try:
        _load_integrate()
    except ImportError as e:
        report["notes"].append(
            f"jaxquat's integrators are not available ({e}): jaxquat rows skipped."
        )
    log(
        f"jaxquat bench, preset {args.preset}: {report['machine']['cpu']}, {report['machine']['cores']} cores"
    )

    # W5 differentiates the problems of W1 (constant ω) and W3 (samples): those rows' problems are
    # kept for it instead of being made again (W3's samples at N = 10⁵: 2.4 GB, ~3.6 s).
    w5_problems = set()
    if "W5" in preset.workloads:
        w5_problems = {
            ("W3" if variant == "sampled" else "W1", dtype, size)
            for variant in preset.w5_variants
            for dtype in preset.w5_dtypes or preset.dtypes
            for size in preset.w5_sizes
        }
    kept: dict[tuple[str, str, int], Problem] = {}
    for workload in ("W1", "W2", "W3"):
        if workload not in preset.workloads:
            continue
        for dtype in preset.dtypes:
            for size in preset.sizes:
                log(f"{workload} {dtype} N={size:,} T={preset.num_steps}")
                problem = make_problem(workload, dtype, size, preset.num_steps)
                row = run_row(problem, preset, log)
                if (workload, dtype, size) in w5_problems:
                    kept[(workload, dtype, size)] = problem
                del problem
                report["rows"].append(row)
                for name, entry in row["contenders"].items():
                    if "rate" in entry:
                        log(f"  {name:40s} {_cell(entry, row)}")
    if "W4" in preset.workloads:
        log("W4 coning work-precision")
        report["w4"] = run_w4(preset, output, log)
    if "W5" in preset.workloads:
        for dtype in preset.w5_dtypes or preset.dtypes:
            for size in preset.w5_sizes:
                for sampled in [v == "sampled" for v in preset.w5_variants]:
                    log(f"W5 {dtype} N={size:,} {'sampled' if sampled else 'constant'} ω")
                    key = ("W3" if sampled else "W1", dtype, size)
                    problem = kept.pop(key, None) or make_problem(*key, preset.num_steps)
                    row = run_w5_row(problem, sampled, preset, log)
                    del problem
                    report["w5"].append(row)
                    for name, entry in row["contenders"].items():
                        if "ratio" in entry:
                            log(f"  {name:12s} grad/forward {entry['ratio']:.2f}")

    report["elapsed_seconds"] = time.perf_counter() - started
    try:
        report["load_average_at_end"] = os.getloadavg()
    except OSError:
        report["load_average_at_end"] = None
    markdown = render_markdown(report)
    (output / "results.md").write_text(markdown + "\n", encoding="utf-8")
    (output / "results.json").write_text(to_json(report) + "\n", encoding="utf-8")
    print(markdown)
    print(f"\nwritten: {output / 'results.md'}, {output / 'results.json'}", flush=True)

    def bad(row) -> bool:  # a wrong answer, or an exception (a crash must not pass as a run)
        entry = row["contenders"].get("jaxquat", {})
        return entry.get("correct") is False or "failed" in entry

    wrong = [
        f"{row['workload']} {row['dtype']} N={row['num_bodies']}"
        for row in report["rows"]
        if bad(row)
    ]
    wrong += [
        f"W5 {row['variant']} {row['dtype']} N={row['num_bodies']}"
        for row in report["w5"]
        if bad(row)
    ]
    if wrong:
        print(
            f"jaxquat bench: jaxquat failed or gave wrong answers in: {'; '.join(wrong)}",
            file=sys.stderr,
        )
        return 1
    return 0
