"""Smoke test of the benchmark suite: the micro preset runs, writes its table, JSON and plot, and every
contender's answer agrees with the closed form. Speed is never asserted here (STYLE.md rule 18)."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxquat import _bench


@pytest.fixture(scope="module")
def micro_report(tmp_path_factory):
    output = tmp_path_factory.mktemp("bench")
    assert _bench.main(["--preset", "micro", "--output", str(output), "--quiet"]) == 0
    return output, json.loads((output / "results.json").read_text())


def test_micro_preset_writes_outputs(micro_report):
    output, report = micro_report
    markdown = (output / "results.md").read_text()
    assert "| W1 | float64 | 3 |" in markdown and "jaxquat ÷ best peer" in markdown
    assert (output / "w4_work_precision.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert report["machine"]["cores"] >= 1
    workloads = {(row["workload"], row["dtype"]) for row in report["rows"]}
    assert workloads == {(w, d) for w in ("W1", "W2", "W3") for d in ("float64", "float32")}


def test_every_contender_agrees_with_the_closed_form(micro_report):
    _, report = micro_report
    for row in report["rows"]:
        tolerance = _bench.ERROR_TOLERANCE[row["dtype"]]
        assert row["contenders"]["jaxquat"]["correct"], row["contenders"]["jaxquat"]
        for name, entry in row["contenders"].items():
            if "skipped" in entry:  # a peer that is not installed
                continue
            where = f"{row['workload']} {row['dtype']} {name}"
            assert "failed" not in entry, f"{where}: {entry['failed']}"
            assert entry["correct"] and entry["error"] <= tolerance, where
            assert entry["rate"] > 0, where
    for row in report["w5"]:
        for name, entry in row["contenders"].items():
            assert entry.get("correct"), f"W5 {row['variant']} {name}: {entry}"
    series = {s["name"]: s for s in report["w4"]["series"]}
    assert {"diffrax Tsit5 (stock)", "jaxquat integrate magnus4"} <= set(series)
    # Fourth-order methods at 256 steps and the adaptive peers at tolerance 1e-9 are all accurate.
    for name in ("jaxquat integrate magnus4", "diffrax Tsit5 (stock)"):
        assert series[name]["points"][0]["error"] < 1e-5, name
    if "numpy-quaternion integrate_angular_velocity" in series:
        assert series["numpy-quaternion integrate_angular_velocity"]["points"][0]["error"] < 1e-6
    assert series["jaxquat integrate euler"]["points"][0]["error"] > 1e-4  # first order is worse


def test_sampled_rates_reproduce_the_closed_form():
    # Stepping exactly through the W3 samples (independent numpy code) lands on exp(aT)exp(bT)q0.
    problem = _bench.make_problem("W3", "float64", 5, 50)
    q = problem.q0
    for omega in np.asarray(problem.omegas):
        q = _bench._q_mul(_bench._q_exp(omega * problem.dt, np), q, np)
    assert np.max(_bench.angle_error(q, problem.expected(50))) < 1e-12
    assert np.max(_bench.angle_error(problem.expected(0), problem.q0)) < 1e-15


def test_float32_sampled_closed_form_uses_the_axis_the_samples_came_from():
    # The float32 samples, stepped exactly in float64, land on the closed form to their own rounding
    # (~1e-7 rad); with a rounded to float32 in the closed form the reference itself was 2.3e-6 off.
    problem = _bench.make_problem("W3", "float32", 200, 1000)
    q = problem.q0.astype(np.float64)
    for omega in np.asarray(problem.omegas, dtype=np.float64):
        q = _bench._q_mul(_bench._q_exp(omega * problem.dt, np), q, np)
    assert np.max(_bench.angle_error(q, problem.expected(1000))) < 5e-7


def test_sampled_rates_match_the_direct_formula():
    # ω_k = log(exp(R(exp(a t_{k+1})) b Δt) ⊗ exp(a Δt))/Δt evaluated term by term, including a = 0.
    rng = np.random.default_rng(3)
    a = np.vstack([2.0 * rng.normal(size=(6, 3)), np.zeros((1, 3))])
    b = 2.0 * rng.normal(size=(7, 3))
    dt, steps = 0.01, 40
    rates = np.asarray(_bench._sampled_rates(a, b, dt, steps))
    for k in range(steps):
        outer = _bench._q_exp(a * (k + 1) * dt, np)
        step = _bench._q_mul(
            _bench._q_exp(_bench._q_rotate(outer, b * dt, np), np), _bench._q_exp(a * dt, np), np
        )
        np.testing.assert_allclose(rates[k], _bench._q_log(step, np) / dt, rtol=0, atol=1e-12)


def _exact_trajectory(problem):
    steps = np.arange(problem.num_steps + 1, dtype=np.float64)[:, None, None]
    rotation = _bench._q_exp(steps * problem.dt * problem.omega[None], np)
    return _bench._q_mul(rotation, problem.q0[None], np)


def test_w2_subset_check_catches_wrong_answers():
    # The quick preset checks W2 on a subset (some bodies at every step, every body at some steps);
    # a wrong body, a wrong step or a wrong norm is still caught, and a right answer passes.
    problem = _bench.make_problem("W2", "float64", 3000, 60)
    exact = _exact_trajectory(problem)
    bodies = _bench.check_bodies(3000, 64)
    steps = _bench.check_steps(60)
    assert len(bodies) <= 64 and {0, 7, 2992, 2999} <= set(bodies)
    assert len(set(bodies % 8)) == 8 and {0, 1, 59, 60} <= set(steps)
    error, norm = problem.trajectory_check(exact, 64)
    assert error < 1e-12 and norm < 1e-12
    assert problem.trajectory_check(exact) == pytest.approx((error, norm), abs=1e-12)

    body = next(i for i in range(3000) if i not in set(bodies))
    wrong = exact.copy()
    wrong[23:, body] = wrong[23:, body][:, [0, 2, 1, 3]]  # one unchecked body, from step 23 on
    assert problem.trajectory_check(wrong, 64)[0] > 1e-3
    step = next(k for k in range(61) if k not in steps)
    wrong = exact.copy()
    wrong[step, :, 1] += 1e-6  # every body, at one unchecked step
    assert problem.trajectory_check(wrong, 64)[0] > 1e-7
    wrong = exact.copy()
    wrong[:, body] *= 1.001  # right rotation, wrong norm
    assert problem.trajectory_check(wrong, 64)[1] > 1e-4


def test_w4_dense_sweeps_name_series_that_run():
    quick = _bench.PRESETS["quick"]
    names = {f"jaxquat integrate {m}" for m in quick.w4_methods}
    names |= {f"jaxquat diffrax {s}" for s in quick.w4_solvers}
    names |= {"diffrax Tsit5 (stock)", "numpy-quaternion integrate_angular_velocity"}
    assert set(dict(quick.w4_sweeps)) <= names
    for name, values in _bench.PRESETS["full"].w4_sweeps:  # the full grid keeps its wide range
        assert set(dict(quick.w4_sweeps)[name]) <= set(values), name


def test_quick_w4_sweeps_bracket_the_target_error():
    """The quick preset runs three step counts of each fixed-step `integrate` method (each is a
    compilation); the two finest must bracket 1e-8 rad with some room, or the time at the target
    would come out as "at most" or "not reached" instead of interpolated."""
    integrate, _ = _bench._load_integrate()
    q0 = jnp.asarray(_bench.coning_exact(0.0))
    exact = _bench.coning_exact(_bench.CONING_END)
    quick = dict(_bench.PRESETS["quick"].w4_sweeps)
    for name, steps in _bench._W4_QUICK_STEPS.items():
        assert quick[name] == steps
        errors = [
            float(
                _bench.angle_error(
                    integrate(
                        q0,
                        lambda t, q=None: _bench.coning_omega(t, jnp),
                        _bench.CONING_END / n,
                        n,
                        method=name.split()[-1],
                        save="final",
                    ),
                    exact,
                )
            )
            for n in steps
        ]
        assert errors == sorted(errors, reverse=True), (name, errors)
        target = _bench.W4_TARGET_ERROR
        assert errors[-1] < 0.97 * target and errors[-2] > 1.03 * target, (name, errors)


def test_w5_reference_gradient_matches_the_closed_form():
    # The hand-written loop (the reference gradient of W5) against the gradient of the closed form.
    problem = _bench.make_problem("W1", "float64", 4, 30)
    forward = _bench._w5_forwards(problem, sampled=False)["JAX loop"]
    q0 = jnp.asarray(problem.q0)
    target = jnp.asarray(_bench.make_problem("W1", "float64", 4, 7).q0)
    t = problem.num_steps * problem.dt

    def closed_form(omega):
        return _bench._q_mul(_bench._q_exp(omega * t, jnp), q0, jnp)

    loss = _bench._loss
    expected = jax.grad(lambda w: loss(closed_form(w), target, jnp))(jnp.asarray(problem.omega))
    actual = jax.grad(lambda w: loss(forward(q0, w), target, jnp))(jnp.asarray(problem.omega))
    np.testing.assert_allclose(actual, expected, rtol=1e-9, atol=1e-12)


def test_time_at_error_interpolates_on_the_pareto_front():
    points = [
        {"seconds": 1.0, "error": 1e-6},
        {"seconds": 2.0, "error": 1e-7},  # dominated by nothing; brackets nothing
        {"seconds": 3.0, "error": 1e-5},  # dominated: slower and less accurate
        {"seconds": 4.0, "error": 1e-9},
    ]
    seconds, how = _bench.time_at_error(points, 1e-8)
    assert how == "interpolated" and seconds == pytest.approx(2.0 * 2.0**0.5)
    assert _bench.time_at_error(points, 1e-12) == (None, "not reached")
    assert _bench.time_at_error(points, 1e-5) == (1.0, "at most")


def test_bad_arguments_exit_with_an_error_code(tmp_path, capsys):
    assert _bench.main(["--preset", "nope", "--output", str(tmp_path)]) == 2
    assert _bench.main(["--workloads", "W9", "--output", str(tmp_path)]) == 2
    assert "W9" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (["--steps", "99999999999999999999999"], "up to 2,147,483,647"),  # was a failed row, exit 0
        (["--sizes", "2,2"], "lists a value twice"),  # every row ran and was reported twice
        (["--dtypes", "float64,float64"], "lists a dtype twice"),
        (["--workloads", "W1,w1"], "lists a workload twice"),
        (["--output", ""], "must name a directory"),  # Path("") wrote into the working directory
    ],
)
def test_bad_option_values_are_one_line_errors(tmp_path, capsys, argv, fragment):
    output = [] if "--output" in argv else ["--output", str(tmp_path)]
    assert _bench.main([*argv, *output]) == 2
    err = capsys.readouterr().err
    assert fragment in err and err.count("\n") == 1, err


def test_a_jaxquat_crash_fails_the_run(tmp_path, monkeypatch, capsys):
    """A jaxquat contender that raised was reported as "failed" in the table and the run exited 0, so
    a broken `integrate` passed a CI that runs the bench."""

    def broken(problem, steps):
        raise RuntimeError("integrate is broken")

    contenders = tuple(
        dataclasses.replace(c, make=broken) if c.role == "jaxquat" else c for c in _bench.CONTENDERS
    )
    monkeypatch.setattr(_bench, "CONTENDERS", contenders)
    argv = ["--workloads", "W1", "--sizes", "3", "--steps", "4", "--repeats", "1", "--quiet"]
    assert _bench.main([*argv, "--dtypes", "float64", "--output", str(tmp_path)]) == 1
    assert "jaxquat failed or gave wrong answers in: W1 float64 N=3" in capsys.readouterr().err


def test_numpy_quaternion_gets_a_plain_numpy_coning_omega():
    """numpy-quaternion's W4 integrator calls ω from Python per stage; it now gets the same ω as plain
    NumPy arithmetic (the generic array helpers cost it ~45× more per call than the formula)."""
    for t in (0.0, 0.37, 2.0, 6.3, -1.1):
        np.testing.assert_allclose(
            _bench.coning_omega_scalar(t),
            _bench.coning_omega(np.float64(t), np),
            rtol=0,
            atol=1e-15,
        )


def test_user_budget_also_holds_for_w2(tmp_path):
    # The quick preset lets W2 peers run all T steps within 2 s; an explicit --budget replaces that.
    argv = ["--workloads", "W1", "--sizes", "3", "--steps", "4", "--repeats", "1", "--quiet"]
    assert _bench.PRESETS["quick"].w2_budget == 2.0
    assert _bench.main([*argv, "--budget", "0.5", "--output", str(tmp_path)]) == 0
    config = json.loads((tmp_path / "results.json").read_text())["config"]
    assert config["budget"] == 0.5 and config["w2_budget"] is None


@pytest.mark.parametrize("sampled", [False, True])
def test_w5_above_the_peer_size_checks_jaxquat_on_a_subset(sampled, monkeypatch):
    # Above `w5_peers_max_bodies` W5 times jaxquat alone and checks its gradient on a subset of bodies
    # against the hand-written loop's gradient of those bodies: right passes, wrong is caught.
    preset = dataclasses.replace(
        _bench.PRESETS["micro"], w5_peers_max_bodies=5, repeats=1, sample_seconds=0.0
    )
    problem = _bench.make_problem("W3" if sampled else "W1", "float64", 40, 12)
    row = _bench.run_w5_row(problem, sampled, preset, lambda message: None)
    assert set(row["contenders"]) == {"jaxquat"}
    assert row["checked_bodies"] == len(_bench.check_bodies(40, 5)) < 40
    entry = row["contenders"]["jaxquat"]
    assert entry["correct"] and entry["gradient_error"] < 1e-10 and entry["ratio"] > 0

    real = _bench._w5_forwards

    def wrong_jaxquat(problem, sampled):  # a 1% error in every body's gradient
        forwards = real(problem, sampled)
        right = forwards["jaxquat"]
        forwards["jaxquat"] = lambda q0, omega: right(q0, 1.01 * omega)
        return forwards

    monkeypatch.setattr(_bench, "_w5_forwards", wrong_jaxquat)
    row = _bench.run_w5_row(problem, sampled, preset, lambda message: None)
    assert row["contenders"]["jaxquat"]["correct"] is False


def test_w5_floor_script_runs_and_checks_its_passes():
    """benchmarks/w5_floor.py (the memory floor under W5's gradient, benchmarks/README.md) runs at a tiny
    size, including a step count that is not a multiple of its three-row blocks, and reports every
    line; its own checks (the floor passes copy and sum the samples exactly) run before any timing.
    Bad sizes are a one-line usage error."""
    import pathlib
    import subprocess
    import sys

    script = pathlib.Path(__file__).parents[1] / "benchmarks" / "w5_floor.py"
    done = subprocess.run(
        [sys.executable, str(script), "--bodies", "5", "--steps", "8", "--repeats", "1"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert "samples: (8, 5, 3) float64" in done.stdout
    for label in ("read", "zero + write", "jaxquat forward", "jaxquat gradient", "floor ÷ read"):
        assert label in done.stdout
    bad = subprocess.run(
        [sys.executable, str(script), "--steps", "0"], capture_output=True, text=True, timeout=300
    )
    assert bad.returncode == 2 and "must be positive integers" in bad.stderr
    assert "Traceback" not in bad.stderr


def test_w4_speedup_from_a_bound_is_marked(tmp_path, monkeypatch):
    """A W4 time that is only a bound ("at most": the cheapest point of the series already beats
    1e-8 rad, e.g. a noisy sample on its Pareto front) made an exact-looking speed-up: numpy-quaternion
    at "≤ 1.84 ms" against magnus8's interpolated 159 µs was reported as "11.5×". The speed-up from a
    peer's upper bound is itself an upper bound, from jaxquat's upper bound a lower bound."""

    def series(name, role, errors_and_seconds):
        points = [{"steps": 1, "error": e, "seconds": s} for e, s in errors_and_seconds]
        return {"name": name, "role": role, "points": points, "note": ""}

    fake = [
        series("jaxquat exact", "jaxquat", [(1e-7, 1e-4), (1e-9, 4e-4)]),  # interpolated: 2e-4 s
        series("peer exact", "peer", [(1e-7, 1e-3), (1e-9, 4e-3)]),  # interpolated: 2e-3 s
        series("peer bound", "peer", [(5e-9, 1e-3), (1e-9, 4e-3)]),  # at most 1e-3 s
    ]
    monkeypatch.setattr(_bench, "_w4_series", lambda preset, log: [dict(s) for s in fake])
    record = _bench.run_w4(_bench.PRESETS["micro"], tmp_path, lambda message: None)
    assert record["best_jaxquat"] == "jaxquat exact"
    assert record["speedups"]["peer exact"] == pytest.approx(10.0)
    assert record["speedups"]["peer bound"] == pytest.approx(5.0)
    assert record["speedup_bounds"] == {"peer exact": "exact", "peer bound": "at most"}
    machine = {
        "cpu": "x",
        "cores": 1,
        "vector_extensions": [],
        "memory": "1 GiB",
        "platform": "p",
        "python": "3",
        "versions": {},
        "load_average_at_start": None,
        "date_utc": "d",
    }
    report = {
        "preset": "micro",
        "machine": machine,
        "elapsed_seconds": 1.0,
        "rows": [],
        "w4": record,
        "w5": [],
        "notes": [],
        "config": {"repeats": 1},
    }
    markdown = _bench.render_markdown(report)
    assert "peer exact 10.0×" in markdown and "peer bound ≤ 5.0×" in markdown, markdown

    # jaxquat's best time an upper bound: its speed-ups are lower bounds.
    fake[0] = series("jaxquat exact", "jaxquat", [(5e-9, 1e-4), (1e-9, 4e-4)])  # at most 1e-4 s
    record = _bench.run_w4(_bench.PRESETS["micro"], tmp_path, lambda message: None)
    assert record["speedup_bounds"] == {"peer exact": "at least", "peer bound": "unknown"}
    assert "peer exact ≥ 20.0×" in _bench.render_markdown({**report, "w4": record})


def test_the_json_report_is_strict_json():
    # A contender returning NaN made its error NaN, written as the non-JSON token NaN (helper-79).
    report = {
        "rows": [{"error": float("nan"), "ratio": np.float64(np.inf), "rate": np.float32(2.5)}]
    }
    text = _bench.to_json(report)

    def refuse(token):
        raise ValueError(token)

    loaded = json.loads(text, parse_constant=refuse)
    assert loaded == {"rows": [{"error": None, "ratio": None, "rate": 2.5}]}
