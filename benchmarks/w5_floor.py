"""The memory floor under W5's sampled-ω gradient, measured beside jaxquat's own forward and gradient.

`python benchmarks/w5_floor.py [--bodies N] [--steps T] [--repeats R]` (float64; default N = 10⁵,
T = 1,000: 2.4 GB of samples). A gradient w.r.t. all samples `(T, N, 3)` must read them once going
forward and once going back, and write a cotangent as large as they are. XLA can only build that
array from a loop by updating a buffer in place, and the buffer is zero-filled first (XLA:CPU has no
uninitialised allocation; `lax.empty` is zeros). This script times those passes alone, with no
arithmetic, and divides by the same read alone (the floor of any forward pass) and by jaxquat's forward:

- *read*: a loop reading the samples three rows at a time and summing them (a forward pass's traffic);
- *zero + write*: `zeros_like`, then a reverse loop writing each three-row block from the samples (an
  adjoint's traffic, without its arithmetic);
- jaxquat's forward (`integrate(..., save="final")` of the samples) and `jax.grad` of W5's loss
  Σ|vec(r̄ ⊗ q_T)|².

See benchmarks/README.md ("Where W5's sampled gradient goes") for what the numbers mean.
"""

import argparse
import functools
import sys

from jaxquat._bench import _autorange, relaunch_with_huge_pages


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bodies", type=int, default=100_000)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args(argv)
    if min(args.bodies, args.steps, args.repeats) < 1:
        parser.error("--bodies, --steps and --repeats must be positive integers")

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    from jax import lax

    import jaxquat as jq

    steps, bodies, dt = args.steps, args.bodies, 0.01
    keys = jax.random.split(jax.random.key(0), 2)
    samples = jax.random.normal(keys[0], (steps, bodies, 3))
    q0 = jq.random(keys[1], (bodies,))
    target = jq.identity((bodies,))

    rest = steps % 3  # the first `rest` rows, read and written on their own

    def read(s):
        def body(k, total):
            block = lax.dynamic_slice_in_dim(s, rest + 3 * k, 3, 0)
            return total + block[0] + block[1] + block[2]

        return lax.fori_loop(0, steps // 3, body, jnp.sum(s[:rest], axis=0))

    def zero_and_write(s):
        def body(k, out):
            start = steps - 3 * (k + 1)
            block = lax.dynamic_slice_in_dim(s, start, 3, 0)
            return lax.dynamic_update_slice_in_dim(out, block, start, 0)

        out = lax.fori_loop(0, steps // 3, body, jnp.zeros_like(s))
        return lax.dynamic_update_slice_in_dim(out, s[:rest], 0, 0)

    def final(s):
        return jq.integrate(q0, jq.sampled(s, dt), dt, steps, save="final")

    def loss(s):
        return jnp.sum(jq.multiply(jq.conjugate(target), final(s))[..., 1:] ** 2)

    # The floor passes must do what they claim: touch every row once, in order.
    np.testing.assert_array_equal(jax.jit(zero_and_write)(samples), samples)
    np.testing.assert_allclose(
        jax.jit(read)(samples), jnp.sum(samples, axis=0), rtol=1e-9, atol=1e-9
    )

    timings = {
        "read": jax.jit(read),
        "zero + write": jax.jit(zero_and_write),
        "jaxquat forward": jax.jit(final),
        "jaxquat gradient": jax.jit(jax.grad(loss)),
    }
    seconds = {
        name: _autorange(functools.partial(f, samples), args.repeats) for name, f in timings.items()
    }
    floor = seconds["read"] + seconds["zero + write"]
    size = samples.size * samples.dtype.itemsize / 1e9
    print(f"samples: ({steps}, {bodies}, 3) float64, {size:.2f} GB; medians of {args.repeats}")
    for name, value in seconds.items():
        print(f"  {name:<17} {value * 1e3:8.1f} ms")
    print(f"  gradient floor (read + zero + write) {floor * 1e3:.1f} ms")
    print(f"  floor ÷ read: {floor / seconds['read']:.2f}")
    print(f"  floor ÷ jaxquat forward: {floor / seconds['jaxquat forward']:.2f}")
    print(
        "  jaxquat gradient ÷ forward: "
        f"{seconds['jaxquat gradient'] / seconds['jaxquat forward']:.2f}"
    )
    return 0


if __name__ == "__main__":
    relaunch_with_huge_pages([__file__, *sys.argv[1:]])
    sys.exit(main(sys.argv[1:]))
