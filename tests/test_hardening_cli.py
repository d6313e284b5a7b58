"""Regression tests for input handling of the command line, the fitting module and the ensemble files.

The command line reports every bad input in one line `jaxquat: error: ...` with exit status 2 (never a
traceback, never exit 0 with NaN or otherwise wrong results); the library raises a `ValueError` naming
the argument and what was expected.
"""

import importlib.util
import json
import os
import subprocess
import sys
import types

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import jaxquat
from jaxquat import _bench, load_ensemble, simulate_ensemble
from jaxquat._cli import main

OMEGA = np.array([0.4, -0.25, 0.7])


def _observations(count=40):
    """Exact orientations of a body turning at the constant rate OMEGA (world frame)."""
    times = np.linspace(0.0, 6.0, count)
    q_start = jaxquat.from_rotvec(jnp.array([0.3, -1.2, 0.5]))
    return times, np.array(jaxquat.multiply(jaxquat.from_rotvec(times[:, None] * OMEGA), q_start))


def _csv_lines(times, qs):
    return [",".join(repr(float(v)) for v in (t, *q)) for t, q in zip(times, qs, strict=True)]


def _write(path, lines, header=True):
    path.write_text("\n".join((["t,w,x,y,z"] if header else []) + list(lines)) + "\n")
    return path


def _run(argv, capsys):
    status = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def _assert_one_line_error(status, out, err, *fragments):
    assert status == 2, (status, out, err)
    assert err.endswith("\n") and err.count("\n") == 1, repr(err)
    assert "Traceback" not in err and "internal error" not in err, err
    for fragment in fragments:
        assert fragment in err, (fragment, err)
    assert out == "", out


def _simulate(tmp_path, *options):
    return [
        "simulate",
        "--bodies",
        "4",
        "--steps",
        "3",
        "--no-progress",
        "--output",
        tmp_path / "run",
        *options,
    ]


# --- 1. values overflowing the working dtype; non-finite results -----------------------------------


@pytest.mark.parametrize(
    "options, fragments",
    [
        (["--omega-scale", "1e39"], ["--omega-scale", "overflows float32"]),
        (["--dt", "1e39"], ["--dt", "overflows float32"]),
        (["--omega-mean", "0,0,-1e39"], ["--omega-mean", "overflows float32"]),
        (["--inertia", "1,2,1e39"], ["--inertia", "overflows float32"]),
        (["--dt", "1e-50"], ["--dt", "underflows float32"]),
    ],
)
def test_simulate_rejects_values_the_dtype_cannot_hold(tmp_path, capsys, options, fragments):
    status, out, err = _run(_simulate(tmp_path, *options), capsys)
    _assert_one_line_error(status, out, err, *fragments)


def test_simulate_toml_value_overflowing_float32_names_the_file(tmp_path, capsys):
    config = tmp_path / "run.toml"
    config.write_text("bodies = 4\nsteps = 3\ndt = 1e39\n")
    status, out, err = _run(["simulate", "--config", config, "--no-progress"], capsys)
    _assert_one_line_error(status, out, err, "run.toml line 3", "dt", "overflows float32")


@pytest.mark.parametrize(
    "options", [["--omega-scale", "1e38"], ["--dt", "1e30", "--omega-scale", "1e10"]]
)
def test_simulate_with_non_finite_results_is_an_error_not_a_summary(tmp_path, capsys, options):
    # Every value is representable in float32, but the run overflows: no summary, exit 2.
    status, out, err = _run(_simulate(tmp_path, *options), capsys)
    _assert_one_line_error(status, out, err, "not finite", "float32")


def test_demo_with_non_finite_results_is_an_error(tmp_path, capsys, monkeypatch):
    def nan_fit(seed):
        fit = types.SimpleNamespace(
            omega=np.full(3, np.nan), residual_angles=np.full(5, np.nan), converged=False
        )
        return np.linspace(0.0, 1.0, 5), np.array(OMEGA), fit

    monkeypatch.setattr("jaxquat._cli._demo_fit", nan_fit)
    png = tmp_path / "demo.png"
    argv = ["demo", "--bodies", "8", "--steps", "4", "--no-progress", "--output", png]
    status = main([str(a) for a in argv])
    captured = capsys.readouterr()
    assert status == 2, captured
    assert captured.err.count("\n") == 1 and "not finite" in captured.err
    assert not png.exists()


def test_demo_steps_beyond_the_int32_step_counter_name_the_option(tmp_path, capsys):
    argv = ["demo", "--steps", "3000000000", "--no-progress", "--output", tmp_path / "out"]
    status, out, err = _run(argv, capsys)
    _assert_one_line_error(status, out, err, "--steps", "at most 2**31 - 1", "3000000000")


def test_toml_steps_beyond_the_int32_step_counter_names_the_file(tmp_path, capsys):
    config = tmp_path / "run.toml"
    config.write_text("bodies = 4\nsteps = 2147483648\n")
    status, out, err = _run(["simulate", "--config", config, "--no-progress"], capsys)
    _assert_one_line_error(status, out, err, "run.toml line 2", "steps", "at most 2**31 - 1")


# --- 2. underdetermined time-varying fits ----------------------------------------------------------


def test_fit_rejects_more_knots_than_the_observations_determine():
    times, qs = _observations(40)
    with pytest.raises(ValueError, match="`knots`.*spline.*at least 5 observations"):
        jaxquat.fit_angular_velocity(times[:3], qs[:3], model="spline")  # default 4 knots
    for model in ("piecewise_linear", "spline"):
        with pytest.raises(ValueError, match=r"`knots`: 1000 knots .* knots <= 39"):
            jaxquat.fit_angular_velocity(times, qs, model=model, knots=1000)
        with pytest.raises(ValueError, match=r"`knots`: 6 knots are too many for 6"):
            jaxquat.fit_angular_velocity(times[:6], qs[:6], model=model, knots=6)
        with pytest.raises(ValueError, match=r"`knots`: 6 knots are too many for 6"):
            jaxquat.fit_angular_velocity(
                times[:6], qs[:6], model=model, knots=np.linspace(0.0, times[5], 6)
            )
    # K = T - 1 is exactly determined: the fit recovers ω.
    fit = jaxquat.fit_angular_velocity(times[:6], qs[:6], model="piecewise_linear", knots=5)
    np.testing.assert_allclose(np.asarray(fit.omega.values), np.tile(OMEGA, (5, 1)), atol=1e-8)


def test_cli_fit_with_too_many_knots_is_a_one_line_error(tmp_path, capsys):
    times, qs = _observations(40)
    three = _write(tmp_path / "three.csv", _csv_lines(times[:3], qs[:3]))
    status, out, err = _run(["fit", three, "--model", "spline"], capsys)
    _assert_one_line_error(status, out, err, "knots", "3 observations")
    full = _write(tmp_path / "full.csv", _csv_lines(times, qs))
    status, out, err = _run(["fit", full, "--model", "spline", "--knots", "1000"], capsys)
    _assert_one_line_error(status, out, err, "knots", "1000")


@pytest.mark.parametrize(
    "options, fragment",
    [
        (["--knots", "5"], "argument --knots: only used with --model piecewise_linear or spline"),
        (
            ["--model", "piecewise_linear", "--knots", "1"],
            "at least 2 for --model piecewise_linear",
        ),
        (["--model", "spline", "--knots", "3"], "at least 4 for --model spline; got 3"),
    ],
)
def test_cli_fit_knots_errors_name_the_option_not_the_file(tmp_path, capsys, options, fragment):
    """A --knots the model cannot use is an option error, said before the file is read (it named the
    CSV file and the library's `knots`, a review); a missing file does not hide it."""
    for path in (
        _write(tmp_path / "obs.csv", _csv_lines(*_observations(40))),
        tmp_path / "none.csv",
    ):
        status, out, err = _run(["fit", path, *options], capsys)
        _assert_one_line_error(status, out, err, fragment)
        assert str(path) not in err


# --- 3. quaternion scales, non-finite times, JSON without NaN -----------------------------------


@pytest.mark.parametrize("scale", [1e160, 1e-170])
def test_fit_normalises_quaternions_of_extreme_scale(tmp_path, capsys, scale):
    times, qs = _observations(40)
    fit = jaxquat.fit_angular_velocity(times, qs * scale)
    np.testing.assert_allclose(np.asarray(fit.omega), OMEGA, atol=1e-8)
    path = _write(tmp_path / "scaled.csv", _csv_lines(times, qs * scale))
    status, out, err = _run(["fit", path, "--json"], capsys)
    assert status == 0, err
    report = json.loads(out)  # strict: NaN would be invalid JSON here
    np.testing.assert_allclose(report["omega"], OMEGA, atol=1e-8)


def test_subnormal_quaternions_are_rejected_naming_the_row(tmp_path, capsys):
    times, qs = _observations(10)
    with pytest.raises(ValueError, match=r"`qs\[0\]` is too small"):
        jaxquat.fit_angular_velocity(times, qs * 1e-320)
    path = _write(tmp_path / "tiny.csv", _csv_lines(times, qs * 1e-320))
    status, out, err = _run(["fit", path, "--json"], capsys)
    _assert_one_line_error(status, out, err, "tiny.csv line 2", "too small")


@pytest.mark.parametrize("bad", [np.inf, -np.inf, np.nan])
def test_fit_rejects_non_finite_times_and_weights(bad):
    times, qs = _observations(10)
    times = times.copy()
    times[-1] = bad
    with pytest.raises(ValueError, match=r"`times` must be finite; times\[9\]"):
        jaxquat.fit_angular_velocity(times, qs)
    with pytest.raises(ValueError, match=r"`times` must be finite"):
        jaxquat.fit_rigid_body(times, qs)
    weights = np.ones(10)
    weights[3] = bad
    with pytest.raises(ValueError, match="`weights` must be finite"):
        jaxquat.fit_angular_velocity(np.linspace(0.0, 1.0, 10), qs, weights=weights)


def test_fit_rejects_times_whose_span_overflows():
    _, qs = _observations(3)
    with pytest.raises(ValueError, match="`times` span"):
        jaxquat.fit_angular_velocity(np.array([-1.5e308, 0.0, 1.5e308]), qs)


def test_cli_fit_never_prints_nan(tmp_path, capsys, monkeypatch):
    times, qs = _observations(10)
    path = _write(tmp_path / "obs.csv", _csv_lines(times, qs))

    def nan_fit(times, qs, **kwargs):
        nan = np.full(3, np.nan)
        return types.SimpleNamespace(
            omega=nan, q0=np.full(4, np.nan), residual_angles=np.full(10, np.nan), converged=True
        )

    monkeypatch.setattr("jaxquat._fitting.fit_angular_velocity", nan_fit)
    for extra in (["--json"], []):
        status, out, err = _run(["fit", path, *extra], capsys)
        _assert_one_line_error(status, out, err, "not finite", "obs.csv")


# --- 4. load_ensemble and simulate_ensemble arguments --------------------------------------------


@pytest.fixture
def run(tmp_path):
    path = tmp_path / "run"
    simulate_ensemble(
        np.tile([1.0, 0, 0, 0], (5, 1)),
        np.ones((5, 3)),
        0.1,
        6,
        save_every=2,
        chunk_size=2,
        statistics=True,
        path=path,
    )
    assert load_ensemble(path)["final"].shape == (5, 4)
    return path


def _edit_index(run, **changes):
    index = json.loads((run / "index.json").read_text())
    index.update(changes)
    (run / "index.json").write_text(json.dumps(index))
    return index


@pytest.mark.parametrize(
    "name, array, fragment",
    [
        ("final.npy", np.zeros((4, 4)), r"final.npy \(final\) holds float64\[4, 4\]"),
        ("final.npy", np.zeros((5, 4), np.float32), r"final.npy \(final\) holds float32"),
        ("total_angle.npy", np.zeros((5, 1)), r"total_angle.npy \(total_angle\) holds"),
        ("final_omega.npy", np.zeros((5, 4)), r"final_omega.npy \(final_omega\) holds"),
    ],
)
def test_load_ensemble_checks_the_final_arrays(run, name, array, fragment):
    np.save(run / name, array)
    with pytest.raises(ValueError, match=fragment):
        load_ensemble(run)


@pytest.mark.parametrize(
    "changes, fragment",
    [
        ({"complete": "false"}, "complete must be true or false"),
        ({"complete": 1}, "complete must be true or false"),
        ({"dt": float("nan")}, "dt must be a finite number"),
        ({"dt": "0.1"}, "dt must be a finite number"),
        ({"t0": float("inf")}, "t0 must be a finite number"),
        ({"num_steps": -6}, "num_steps must be an integer >= 0"),
        ({"steps_done": -1}, "steps_done must be an integer >= 0"),
        ({"steps_done": 7}, "steps_done 7 exceeds num_steps 6"),
        ({"save_every": 0}, "save_every must be an integer >= 1"),
        ({"batch_shape": [-5]}, "batch_shape must be a list of non-negative integers"),
        ({"batch_shape": ["5"]}, "batch_shape must be a list of non-negative integers"),
        ({"dtype": "int8"}, "dtype must name a float dtype"),
        ({"final": {"final": "final.npy", "bogus": "final.npy"}}, "unknown final array"),
        # The run's account must agree with itself (these loaded, the metadata saying 9 bodies).
        ({"num_bodies": 9}, r"num_bodies 9 is not the number of bodies of batch_shape \[5\] \(5\)"),
        ({"num_bodies": True}, "num_bodies True is not the number of bodies"),
        ({"frame": "sideways"}, "frame must be one of world, body; got 'sideways'"),
        ({"method": 5}, "method must be one of euler, .*; got 5"),
    ],
)
def test_load_ensemble_validates_the_index(run, changes, fragment):
    _edit_index(run, **changes)
    with pytest.raises(ValueError, match=fragment):
        load_ensemble(run)


def test_load_ensemble_refuses_a_key_given_twice(run):
    """JSON keeps the last of two equal keys: `"dt": 0.01, "dt": 0.02` in an edited index loaded
    with every saved time doubled while the run's metadata still said 0.01 (helper-49)."""
    text = (run / "index.json").read_text()
    assert load_ensemble(run)["metadata"]["dt"] == 0.1 and text.count('"dt": 0.1,') == 1
    (run / "index.json").write_text(text.replace('"dt": 0.1,', '"dt": 0.1, "dt": 0.2,'))
    with pytest.raises(ValueError, match=r"index.json gives 'dt' twice"):
        load_ensemble(run)


def test_load_ensemble_rejects_negative_saved_steps(run):
    index = json.loads((run / "index.json").read_text())
    index["records"][1]["steps"] = [-2]
    (run / "index.json").write_text(json.dumps(index))
    with pytest.raises(ValueError, match="saved steps must be non-negative"):
        load_ensemble(run)


@pytest.mark.parametrize("where", ["record", "final"])
@pytest.mark.parametrize("kind", ["parent", "absolute"])
def test_load_ensemble_reads_nothing_outside_its_directory(run, tmp_path, where, kind):
    index = json.loads((run / "index.json").read_text())
    inside = run / (index["records"][1]["files"]["states"] if where == "record" else "final.npy")
    outside = tmp_path / "outside.npy"
    outside.write_bytes(inside.read_bytes())  # a valid array, so only the name is wrong
    name = "../outside.npy" if kind == "parent" else str(outside)
    if where == "record":
        index["records"][1]["files"]["states"] = name
    else:
        index["final"]["final"] = name
    (run / "index.json").write_text(json.dumps(index))
    with pytest.raises(ValueError, match="expected a plain .npy file name"):
        load_ensemble(run)


@pytest.mark.parametrize("path", [None, 3, ""])
def test_load_ensemble_path_argument(path):
    with pytest.raises(ValueError, match="`path`"):
        load_ensemble(path)


def test_simulate_ensemble_rejects_step_counts_beyond_int32(tmp_path, capsys):
    # Step indices are int32 on the device: 2**31 steps would wrap to negative times, silently.
    with pytest.raises(ValueError, match=r"`num_steps` must be at most 2\*\*31 - 1"):
        simulate_ensemble(np.tile([1.0, 0, 0, 0], (2, 1)), np.ones((2, 3)), 0.1, 2**31)
    argv = _simulate(tmp_path)
    argv[argv.index("--steps") + 1] = str(2**31)
    status, out, err = _run(argv, capsys)
    _assert_one_line_error(status, out, err, "--steps", "2147483647")


@pytest.mark.parametrize("t0", ["a", None, [0.0, 1.0], 1 + 2j, float("nan")])
def test_simulate_ensemble_rejects_bad_t0(t0):
    with pytest.raises(ValueError, match="`t0`"):
        simulate_ensemble(np.array([[1.0, 0, 0, 0]]), np.ones((1, 3)), 0.1, 2, t0=t0)


def test_simulate_ensemble_rejects_non_finite_dt():
    with pytest.raises(ValueError, match="`dt` must be finite"):
        simulate_ensemble(np.array([[1.0, 0, 0, 0]]), np.ones((1, 3)), float("inf"), 2)


def test_simulate_ensemble_takes_dt_and_t0_alike():
    """`dt=True` ran with dt = 1 where `t0=True` was refused; an integer t0 was accepted eagerly and
    refused traced (under jax.jit). Bools are refused for both; integers taken for both, traced too."""
    q0, omega = np.array([[1.0, 0, 0, 0]]), np.ones((1, 3))
    for name, dt, t0 in (("dt", True, 0.0), ("dt", np.bool_(True), 0.0), ("t0", 0.1, True)):
        with pytest.raises(ValueError, match=f"`{name}` must be a real scalar"):
            simulate_ensemble(q0, lambda t, q: omega * t, dt, 2, t0=t0)

    def final(t0):
        return simulate_ensemble(q0, lambda t, q: omega * t, 0.1, 2, t0=t0).final

    np.testing.assert_allclose(jax.jit(final)(3), final(3), rtol=0, atol=1e-15)
    np.testing.assert_allclose(final(3), final(3.0), rtol=0, atol=0)


# --- 5. bench arguments --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "argv, fragments",
    [
        (["--sizes", "a,b"], ["--sizes", "'a,b'"]),
        (["--repeats", "0"], ["--repeats", "positive"]),
        (["--repeats", "-3"], ["--repeats", "positive"]),
        (["--w5-sizes", "0"], ["--w5-sizes", "positive"]),
        (["--w5-sizes", "-2"], ["--w5-sizes"]),
        (["--steps", "x"], ["--steps"]),
        (["--budget", "nan"], ["--budget"]),
        (["--preset", "huge"], ["--preset", "invalid choice"]),
        (["--bogus"], ["unrecognized arguments"]),
        # A repeated option kept the last silently; an empty list ran the whole preset.
        (["--steps", "5", "--steps", "6"], ["--steps", "only once", "got 5 and then 6"]),
        (["--workloads", "W1", "--workloads", "W2"], ["--workloads", "only once"]),
        (["--workloads", ""], ["--workloads", "''"]),
        (["--workloads", "W1,"], ["--workloads", "'W1,'"]),
        (["--dtypes", ""], ["--dtypes", "''"]),
    ],
)
def test_bench_argument_errors_are_one_line(argv, fragments, tmp_path, capsys, monkeypatch):
    def must_not_run():
        raise AssertionError("the suite started despite a bad argument")

    monkeypatch.setattr(_bench, "describe_machine", must_not_run)
    status, out, err = _run(["bench", "--no-huge-pages", "--output", tmp_path, *argv], capsys)
    _assert_one_line_error(status, out, err, "jaxquat bench: error:", *fragments)


# --- 6. solver names -----------------------------------------------------------------------------


def test_fit_solver_must_be_an_optimistix_solver():
    times, qs = _observations(10)
    with pytest.raises(ValueError, match="`solver`.*LevenbergMarquardt.*GaussNewton.*'lm'"):
        jaxquat.fit_angular_velocity(times, qs, solver="lm")
    with pytest.raises(ValueError, match="`solver`"):
        jaxquat.fit_rigid_body(times, qs, solver="lm")
    fit = jaxquat.fit_angular_velocity(times, qs, solver=optx.Dogleg(rtol=1e-8, atol=1e-8))
    np.testing.assert_allclose(np.asarray(fit.omega), OMEGA, atol=1e-6)


# --- 7. command-line details ---------------------------------------------------------------------


@pytest.mark.parametrize("seed", ["99999999999999999999999", "-1", "4294967296", "1_0", "x"])
@pytest.mark.parametrize("command", ["simulate", "demo"])
def test_seed_out_of_range_is_a_one_line_error(tmp_path, capsys, seed, command):
    status, out, err = _run(
        [command, "--seed", seed, "--no-progress", "--output", tmp_path / "x.png"], capsys
    )
    _assert_one_line_error(status, out, err, "--seed")


def test_empty_output_names_the_option(tmp_path, capsys):
    status, out, err = _run(_simulate(tmp_path)[:-2] + ["--output", ""], capsys)
    _assert_one_line_error(status, out, err, "--output", "''")
    status, out, err = _run(["demo", "--output", ""], capsys)
    _assert_one_line_error(status, out, err, "--output", "''")


@pytest.mark.parametrize(
    "line, fragments",
    [
        ('dt = "0.1"', ["line 2", "dt", "number"]),
        ('omega_scale = "1"', ["line 2", "omega_scale"]),
        ('omega_mean = ["0.1", 0, 0]', ["line 2", "omega_mean"]),
        ('inertia = [1, "2", 3]', ["line 2", "inertia"]),
        ('bodies = "4"', ["line 2", "bodies"]),
        ("seed = 99999999999999999", ["line 2", "seed"]),
        ('frame = "sideways"', ["line 2", "frame", "sideways"]),
        ('dtype = "float16"', ["line 2", "dtype", "float16"]),
        ('method = "heun"', ["line 2", "method", "heun"]),
        ('output = ""', ["line 2", "output"]),
    ],
)
def test_toml_values_are_checked_and_errors_name_the_file(tmp_path, capsys, line, fragments):
    config = tmp_path / "conf.toml"
    config.write_text(f"steps = 2\n{line}\n")
    status, out, err = _run(
        ["simulate", "--config", config, "--no-progress", "--output", tmp_path / "run"], capsys
    )
    _assert_one_line_error(status, out, err, "conf.toml", *fragments)


def test_toml_method_invalid_for_rigid_bodies_names_the_file(tmp_path, capsys):
    config = tmp_path / "rigid.toml"
    config.write_text('bodies = 3\nsteps = 2\ninertia = [1, 2, 3]\nmethod = "magnus4"\n')
    status, out, err = _run(
        ["simulate", "--config", config, "--no-progress", "--output", tmp_path / "run"], capsys
    )
    _assert_one_line_error(status, out, err, "rigid.toml line 4", "magnus4")


@pytest.mark.parametrize("field", ["1_0", "١", "0x1", "1e"])
def test_csv_numbers_are_plain_decimals(tmp_path, capsys, field):
    times, qs = _observations(6)
    lines = _csv_lines(times, qs)
    lines[2] = ",".join([field, *lines[2].split(",")[1:]])
    path = _write(tmp_path / "odd.csv", lines)
    status, out, err = _run(["fit", path], capsys)
    _assert_one_line_error(status, out, err, "line 4", "column t", "not a number")


@pytest.mark.parametrize("typo", ["0.O", "abc", "1..0"])
def test_typo_in_the_first_data_row_is_a_data_error(tmp_path, capsys, typo):
    times, qs = _observations(6)
    lines = _csv_lines(times, qs)
    fields = lines[0].split(",")
    fields[3] = typo
    lines[0] = ",".join(fields)
    path = _write(tmp_path / "typo.csv", lines, header=False)
    status, out, err = _run(["fit", path], capsys)
    _assert_one_line_error(status, out, err, "line 1", "column y", repr(typo))
    assert "header" not in err


class JaxRuntimeError(RuntimeError):
    """Stands in for `jax.errors.JaxRuntimeError` (matched by name, as XLA raises it)."""


@pytest.mark.parametrize(
    "error",
    [
        MemoryError("Unable to allocate 1.2 TiB for an array"),
        MemoryError(),
        JaxRuntimeError("INTERNAL: Out of memory allocating 1200000000000 bytes."),
        JaxRuntimeError("RESOURCE_EXHAUSTED: failed to allocate"),
    ],
    ids=["numpy", "bare", "xla-internal", "xla-resource-exhausted"],
)
def test_out_of_memory_is_a_one_line_user_error(tmp_path, capsys, monkeypatch, error):
    # Arguments too large for the machine are the user's to change (exit 2, one line naming the
    # options), not an internal error; any other unexpected exception still is (exit 1).
    def fail(*args, **kwargs):
        raise error

    monkeypatch.setattr("jaxquat._ensemble.simulate_ensemble", fail)
    status, out, err = _run(_simulate(tmp_path), capsys)
    _assert_one_line_error(status, out, err, "out of memory", "--bodies", "--chunk-size")
    assert "()" not in err  # a bare MemoryError has no reason to show


def test_unexpected_runtime_error_is_still_internal(tmp_path, capsys, monkeypatch):
    def fail(*args, **kwargs):
        raise JaxRuntimeError("INTERNAL: something else broke")

    monkeypatch.setattr("jaxquat._ensemble.simulate_ensemble", fail)
    status, out, err = _run(_simulate(tmp_path), capsys)
    assert status == 1 and err.count("\n") == 1 and "internal error" in err, (status, err)
    assert "Traceback" not in err


def test_vectors_accept_spaces_after_commas():
    from jaxquat._cli import _inertia, _vector3

    assert _vector3("0, 0, 1") == [0.0, 0.0, 1.0]
    assert _inertia(" 1, 2 ,3 ") == [1.0, 2.0, 3.0]


def test_fit_accepts_bfloat16_observations():
    # The concrete-input row check must not use np.finfo, which does not know bfloat16.
    times = jnp.linspace(0.0, 1.0, 8)
    qs = jaxquat.integrate(jnp.array([1.0, 0, 0, 0]), jnp.array([0.3, 0.2, 0.1]), 1 / 7, 7)
    fit = jaxquat.fit_angular_velocity(times.astype(jnp.bfloat16), qs.astype(jnp.bfloat16))
    assert fit.omega.dtype == jnp.bfloat16
    np.testing.assert_allclose(np.asarray(fit.omega, np.float64), [0.3, 0.2, 0.1], atol=3e-3)


# --- 8. load_ensemble on damaged or inconsistent runs; genuine runs ------------------------------


def _rewrite_index(run, edit):
    index = json.loads((run / "index.json").read_text())
    edit(index)
    (run / "index.json").write_text(json.dumps(index))


def _unclosed_header(run):
    """final.npy's header with its shape's `)` blanked: NumPy's header parser then tokenizes it and
    raises tokenize.TokenError, which is neither a ValueError nor an OSError."""
    data = (run / "final.npy").read_bytes()
    end = data.index(b"), }")
    (run / "final.npy").write_bytes(data[:end] + b" " + data[end + 1 :])


def _huge_step_counts(index):
    index.update(steps_done=10**20, num_steps=10**20, complete=False)
    index["records"][-1]["steps"] = [10**19]


@pytest.mark.parametrize(
    "damage, message",
    [
        (
            lambda run: (run / "states_000001.npy").write_bytes(b""),  # was an EOFError
            r"states_000001.npy, record 1 \(states\), is not a readable .npy file \(.*EOF",
        ),
        (
            _unclosed_header,  # was a tokenize.TokenError
            r"final.npy, .*is not a readable .npy file \(TokenError",
        ),
        (
            lambda run: _rewrite_index(run, _huge_step_counts),  # was an OverflowError
            r"index.json: num_steps must be at most 2\*\*31 - 1 = 2147483647, got 10{20}",
        ),
        (
            lambda run: (run / "index.json").write_text("[" * 100_000 + "]" * 100_000),
            "index.json is nested too deeply",  # was a RecursionError
        ),
        (
            lambda run: _rewrite_index(run, lambda index: index.update(version=99)),
            r"index.json: format version 99 is not one this jaxquat reads \(version 1\)",
        ),
        (
            lambda run: _rewrite_index(run, lambda index: index.update(dt=1e308)),
            r"index.json: the time t0 \+ k·dt of saved step k = 2 is not finite",
        ),
        (
            lambda run: _rewrite_index(run, lambda index: index.update(final={})),
            "index.json: complete, but final lacks final, final_omega, angle_from_start",
        ),
        (
            lambda run: _rewrite_index(run, lambda index: index.update(records=[])),
            "index.json: complete, but its records hold 0 saved states where save_every 2 and "
            "steps_done 6 make 4",
        ),
        (
            lambda run: _rewrite_index(run, lambda index: index["records"].pop(2)),
            "index.json: complete, but its records hold 3 saved states",
        ),
        (
            lambda run: _rewrite_index(run, lambda index: index["records"][2].update(steps=[3])),
            r"index.json: complete, but saved step 3 is not step 4 \(every save_every 2 steps",
        ),
    ],
    ids=[
        "empty-npy",
        "unclosed-header",
        "huge-steps",
        "deep-json",
        "version",
        "times-overflow",
        "no-final",
        "no-records",
        "missing-record",
        "wrong-step",
    ],
)
def test_load_ensemble_names_the_damaged_file(run, damage, message):
    damage(run)
    with pytest.raises(ValueError, match=message):
        load_ensemble(run)


@pytest.mark.parametrize("interrupted", [False, True], ids=["complete", "interrupted"])
@pytest.mark.parametrize("save_every", [None, 3])
@pytest.mark.parametrize("dynamic", [False, True], ids=["kinematic", "rigid"])
def test_load_ensemble_reads_every_genuine_run(tmp_path, dynamic, save_every, interrupted):
    # 10 steps in chunks of 3: the last chunk is one step, with no state to save.
    def progress(done, total):
        if interrupted and done >= 6:
            raise KeyboardInterrupt

    args = (np.tile([1.0, 0, 0, 0], (5, 1)), np.tile([0.1, 0.2, 0.3], (5, 1)), 0.1, 10)
    kwargs = dict(save_every=save_every, chunk_size=3, path=tmp_path / "run", progress=progress)
    if dynamic:
        kwargs["inertia"] = np.array([1.0, 2.0, 3.0])
    if interrupted:
        with pytest.raises(KeyboardInterrupt):
            simulate_ensemble(*args, **kwargs)
    else:
        simulate_ensemble(*args, **kwargs)
    data = load_ensemble(tmp_path / "run")
    done = 6 if interrupted else 10
    assert data["complete"] is not interrupted and data["steps_done"] == done and data["finite"]
    assert data["steps"].tolist() == (list(range(0, done + 1, 3)) if save_every else [])
    assert data["states"].shape == (len(data["steps"]), 5, 4)
    assert ("omegas" in data) is dynamic and ("final" in data) is not interrupted


def test_load_ensemble_marks_results_that_are_not_finite(tmp_path, capsys):
    # The CLI reports the overflow and keeps the run on disk: load_ensemble says it is not finite.
    options = ["--dt", "1e30", "--omega-scale", "1e10", "--save-every", "1"]
    status, out, err = _run(_simulate(tmp_path, *options), capsys)
    _assert_one_line_error(status, out, err, "not finite", "or --dtype float64")
    data = load_ensemble(tmp_path / "run")
    assert data["complete"] and not data["finite"]


# --- 9. command-line review: bounds, one-line errors that name the option or the line -----------


@pytest.mark.parametrize("bodies", [10**20, 2**63 - 1, 2**40 + 1])
@pytest.mark.parametrize("command", ["simulate", "demo"])
def test_bodies_beyond_any_machine_name_the_option(tmp_path, capsys, command, bodies):
    argv = [command, "--bodies", bodies, "--steps", "1", "--no-progress"]
    status, out, err = _run([*argv, "--output", tmp_path / "out.png"], capsys)
    _assert_one_line_error(status, out, err, "--bodies", "at most 2**40", str(bodies))


def test_toml_bodies_beyond_any_machine_names_the_file(tmp_path, capsys):
    config = tmp_path / "run.toml"
    config.write_text("steps = 1\nbodies = 9223372036854775807\n")
    status, out, err = _run(["simulate", "--config", config, "--no-progress"], capsys)
    _assert_one_line_error(status, out, err, "run.toml line 2", "bodies", "at most 2**40")


# Exact observations of ω = (1, 1, 1)·scale, 1e-160 s (1e200 s) apart: 0.17 rad per interval.
_SPINNING = [
    "0.92338051687663869,0.10259783520851541,0.20519567041703082,0.30779350562554619",
    "0.88917911277087114,0.15344815172937834,0.24029104005963228,0.35787481918948211",
    "0.8483130323045458,0.20314832622068418,0.27358535298448344,0.4052737487283834",
    "0.80108857956929169,0.25132584028508154,0.30482905787272818,0.44963502439765241",
]


def _about_x(origin: str, interval: str) -> list[str]:
    """Exact rows of ω = (0.5, 0, 0) at times origin + k·interval (written in decimal, k < 12)."""
    import decimal

    from scipy.spatial.transform import Rotation

    rows = []
    for k in range(12):
        t = decimal.Decimal(origin) + k * decimal.Decimal(interval)
        x, y, z, w = (
            float(c) for c in Rotation.from_rotvec([0.5 * k * float(interval), 0, 0]).as_quat()
        )
        rows.append(f"{t},{w!r},{x!r},{y!r},{z!r}")
    return rows


@pytest.mark.parametrize(
    "origin, interval",
    [
        ("1000000000000000", "0.3"),  # doubles 0.125 apart: read as is, |ω| came out 0.49855
        ("1000000000000000", "0.01"),  # all twelve read as one double: "times must increase"
        ("1700000000", "0.0001"),  # Unix seconds at 10 kHz (doubles 2.4e-7 s apart): refused
        ("1700000000", "0.001"),
        ("1e15", "1"),
        ("0", "0.3"),
    ],
)
def test_fit_counts_far_times_exactly_from_the_first(tmp_path, capsys, origin, interval):
    """Times far from zero are coarse in float64: 0.3 s steps from 1e15 read as multiples of 0.125
    and fitted |ω| = 0.49855 instead of 0.5, converged, with nothing said (helper-49); then they
    were refused, and so were Unix times in seconds at 10 kHz. Now the file's times are counted
    from its first, exactly (in decimal), before they are rounded: the fit is the closed form's."""
    import decimal

    path = _write(tmp_path / "far.csv", _about_x(origin, interval))
    status, out, err = _run(["fit", path, "--json"], capsys)
    assert status == 0, err
    report = json.loads(out)
    np.testing.assert_allclose(report["omega"], [0.5, 0, 0], rtol=1e-9, atol=1e-9)
    assert report["t0"] == float(decimal.Decimal(origin))
    assert max(report["residual_max_deg"], 0) < 1e-6
    # The time-varying models report their knots on the file's clock, printed apart.
    status, out, err = _run(["fit", path, "--json", "--model", "piecewise_linear"], capsys)
    assert status == 0, err
    report = json.loads(out)
    span = [decimal.Decimal(origin), decimal.Decimal(origin) + 11 * decimal.Decimal(interval)]
    assert [report["knots"][0], report["knots"][-1]] == [float(span[0]), float(span[1])]
    np.testing.assert_allclose(
        report["omega_at_knots"], [[0.5, 0, 0]] * len(report["knots"]), atol=1e-6
    )
    np.testing.assert_allclose(
        report["knots_from_t0"], np.linspace(0, 11 * float(interval), len(report["knots"]))
    )
    status, out, err = _run(["fit", path, "--model", "piecewise_linear", "--knots", "5"], capsys)
    assert status == 0, err
    # Each knot printed to 6 digits of its spacing, on the file's clock or from t0 when far.
    labels = [line[6:].split("omega")[0].strip() for line in out.splitlines() if "omega =" in line]
    origin_value = float(origin) if "t0 + " not in labels[1] else 0.0
    printed = np.array([float(label.removeprefix("t0 + ")) - origin_value for label in labels])
    spacing = 11 * float(interval) / 4
    np.testing.assert_allclose(printed, spacing * np.arange(5), rtol=0, atol=1e-5 * spacing)
    assert f"at t0 = {_about_x(origin, interval)[0].split(',')[0]} " in out


@pytest.mark.parametrize(
    "times, message",
    [
        # An exponent beyond Decimal's range (±10¹⁸): the time reads as 0 (was an internal error).
        (["0", "1e-99999999999999999999999", "1"], "line 3: times must increase, but t = 1e-"),
        # Offsets that differ beyond their 60th digit: read as one double (was the library's
        # "must be strictly increasing", naming no line).
        (["0", "1", "1." + "0" * 66 + "1", "2"], "line 4: float64 cannot tell the time 1.0000"),
        # Offsets below float64's range (were rounded to 0 by the decimal context and accepted).
        (["0", "1e-2000000", "2e-2000000", "3e-2000000"], "line 3: float64 holds the time 1e-2"),
    ],
)
def test_fit_times_beyond_decimal_or_float64_are_one_line_errors(tmp_path, capsys, times, message):
    rows = [r.split(",", 1)[1] for r in _about_x("0", "0.5")[: len(times)]]
    path = _write(tmp_path / "odd.csv", [f"{t},{q}" for t, q in zip(times, rows, strict=True)])
    status, out, err = _run(["fit", path], capsys)
    _assert_one_line_error(status, out, err, f"odd.csv {message}")


def test_fit_reports_t0_and_knots_rounded_once(tmp_path, capsys):
    """1e15 + 0.0625 + 1e-20 is nearer 1e15 + 0.125 than 1e15: 28-digit decimal sums rounded it
    to the tie first, and then to 1e15 (helper-51)."""
    rows = _about_x("1000000000000000.1", "0.3")
    rows[0] = "1000000000000000.06250000000000000001," + rows[0].split(",", 1)[1]
    path = _write(tmp_path / "tie.csv", rows)
    status, out, err = _run(["fit", path, "--json"], capsys)
    assert status == 0, err
    assert json.loads(out)["t0"] == 1000000000000000.125
    zero = _write(
        tmp_path / "zero.csv",
        [
            "-1," + rows[0].split(",", 1)[1],
            *(
                f"{t},{q}"
                for t, q in zip(
                    ["0e99999999999999999999999", "1"],
                    [r.split(",", 1)[1] for r in rows[1:3]],
                    strict=True,
                )
            ),
        ],
    )
    status, out, err = _run(["fit", zero, "--json"], capsys)
    assert status == 0 and json.loads(out)["t0"] == -1.0, err


def test_fit_times_too_coarse_even_from_the_first_are_refused(tmp_path, capsys):
    """Intervals of 1e-12 s in a file spanning 1000 s: float64 holds 1000 s only to 1.1e-13."""
    rows = [r.split(",", 1)[1] for r in _about_x("0", "1e-12")[:4]]
    times = ["0", "1e-12", "2e-12", "1000.0000000000000301"]
    path = _write(tmp_path / "span.csv", [f"{t},{q}" for t, q in zip(times, rows, strict=True)])
    status, out, err = _run(["fit", path], capsys)
    _assert_one_line_error(
        status, out, err, "span.csv line 5", "1000.0000000000000301", "3.01e-14 s", "1e-12"
    )


def test_fit_times_that_decrease_within_one_double_are_refused(tmp_path, capsys):
    rows = [r.split(",", 1)[1] for r in _about_x("0", "0.01")[:3]]
    times = ["1000000000000000.01", "1000000000000000.03", "1000000000000000.02"]
    path = _write(tmp_path / "order.csv", [f"{t},{q}" for t, q in zip(times, rows, strict=True)])
    status, out, err = _run(["fit", path], capsys)
    _assert_one_line_error(
        status,
        out,
        err,
        "order.csv line 4",
        "t = 1000000000000000.02 follows t = 1000000000000000.03",
    )


@pytest.mark.parametrize("interval, omega", [("e-160", 1e159), ("e+200", 1e-201)])
def test_fit_omega_norm_neither_overflows_nor_underflows(tmp_path, capsys, interval, omega):
    rows = [f"{k}{interval},{q}" if k else f"0,{q}" for k, q in enumerate(_SPINNING)]
    path = _write(tmp_path / "spin.csv", rows)
    status, out, err = _run(["fit", path, "--json"], capsys)
    assert status == 0, err
    report = json.loads(out)
    np.testing.assert_allclose(report["omega"], [omega] * 3, rtol=1e-9)
    assert report["omega_norm"] == pytest.approx(3**0.5 * omega, rel=1e-9)
    status, out, err = _run(["fit", path], capsys)
    assert status == 0 and f"|omega| = {3**0.5 * omega:.9g}," in out, (out, err)


@pytest.mark.parametrize("separator", ["\u2028", "\u2029", "\x85", "\x0c", "\x1c", "\x1d", "\x1e"])
def test_csv_line_numbers_count_only_line_ends(tmp_path, capsys, separator):
    # Editors, `wc -l` and `sed -n 5p` count LF (CR LF, CR): so must the message.
    times, qs = _observations(6)
    lines = [f"# exported{separator}by the tracker", *_csv_lines(times, qs)]
    lines[3] = lines[3].rsplit(",", 1)[0] + ",oops"
    path = _write(tmp_path / "obs.csv", lines)
    status, out, err = _run(["fit", path], capsys)
    _assert_one_line_error(status, out, err, "obs.csv line 5:", "column z", "'oops'")


@pytest.mark.parametrize("header", [True, False])
@pytest.mark.parametrize("separator", [";", "\t", " "])
def test_csv_with_another_separator_says_so(tmp_path, capsys, separator, header):
    times, qs = _observations(6)
    lines = [line.replace(",", separator) for line in _csv_lines(times, qs)]
    path = _write(tmp_path / "semicolons.csv", lines, header=False)
    if header:
        path.write_text(f"t{separator}w{separator}x{separator}y{separator}z\n" + path.read_text())
    status, out, err = _run(["fit", path], capsys)
    _assert_one_line_error(status, out, err, "line 1:", "separated by commas", repr(separator))
    assert "header" not in err


def test_config_given_twice_is_an_error_naming_it(tmp_path, capsys):
    first, second = tmp_path / "first.toml", tmp_path / "second.toml"
    first.write_text("bodies = 7\nbogus_key = 1\n")  # would otherwise be silently ignored
    second.write_text("steps = 2\n")
    argv = ["simulate", "--config", first, "--config", second, "--no-progress"]
    status, out, err = _run([*argv, "--output", tmp_path / "run"], capsys)
    _assert_one_line_error(status, out, err, "--config", "only once", "first.toml", "second.toml")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    "text, line",
    [
        ('output = """\nrun\ndt = 5\n"""\ndt = -1\n', None),  # the key's text in a string too
        ("output = '''run\ndt = 5'''\ndt = -1\n", None),
        ("inertia = [\n  1, # dt = 5\n  2, 3,\n]\ndt = -1\n", 5),  # in a comment: not a key
        ("# settings\n'dt' = -1\n", 2),  # quoted keys
        ('steps = 2\n"d\\u0074" = -1\n', None),  # an escaped one
        # The key's text in a string once, and the key itself escaped: the string's line was named.
        ('output = """o_ml\ndt = 10"""\n"d\\u0074" = -1\n', None),
        ("simulate.dt = -1\n", 1),  # a dotted key
        ("simulate = {steps = 2, dt = -1}\n", None),  # an inline table
        ("[simulate]\nsteps = 2\n\ndt = -1\n", 4),  # a table
    ],
)
def test_toml_errors_name_the_line_of_the_key_or_no_line(tmp_path, capsys, text, line):
    """The line is named when one line plainly sets the key, and otherwise none: never a wrong line
    (the key's text in a multi-line string once named that line)."""
    config = tmp_path / "conf.toml"
    config.write_text(text)
    status, out, err = _run(
        ["simulate", "--config", config, "--no-progress", "--output", tmp_path / "run"], capsys
    )
    where = "conf.toml" if line is None else f"conf.toml line {line}"
    _assert_one_line_error(status, out, err, f"{where}: dt must be positive")
    if line is None:
        assert " line " not in err


def test_option_underflowing_to_zero_says_so(tmp_path, capsys):
    status, out, err = _run(_simulate(tmp_path, "--dt", "1e-400"), capsys)
    _assert_one_line_error(status, out, err, "--dt", "'1e-400' underflows to 0")


@pytest.mark.parametrize(
    ("line", "fragments"),
    [
        ("dt = 1e-400", ("line 2", "dt", "'1e-400' underflows to 0")),
        ("omega_scale = 1_0e-4_00", ("line 2", "omega_scale", "'10e-400' underflows to 0")),
        ("omega_mean = [0.0, 2e-324, 1]", ("line 2", "omega_mean", "'2e-324' underflows to 0")),
    ],
)
def test_toml_number_underflowing_to_zero_says_so(tmp_path, capsys, line, fragments):
    """tomllib reads 1e-400 as 0.0; the file's own text is what the message quotes (it once said
    "must be positive, got 0")."""
    config = tmp_path / "conf.toml"
    config.write_text(f"steps = 2\n{line}\n")
    status, out, err = _run(
        ["simulate", "--config", config, "--no-progress", "--output", tmp_path / "run"], capsys
    )
    _assert_one_line_error(status, out, err, "conf.toml", *fragments)


def test_toml_zero_and_underscored_numbers_are_still_read(tmp_path):
    from jaxquat._cli import read_simulate_toml

    config = tmp_path / "conf.toml"
    config.write_text("dt = 1_0.0e-3\nomega_scale = 0.0\nomega_mean = [0.0, -0e5, 1_000.5]\n")
    read = read_simulate_toml(str(config))
    assert read == {"dt": 0.01, "omega_scale": 0.0, "omega_mean": [0.0, 0.0, 1000.5]}
    assert all(type(v) is float for v in [read["dt"], read["omega_scale"], *read["omega_mean"]])


def test_non_finite_float64_results_do_not_advise_float64(tmp_path, capsys):
    options = ["--dt", "1e300", "--omega-scale", "1e10", "--dtype", "float64"]
    status, out, err = _run(_simulate(tmp_path, *options), capsys)
    _assert_one_line_error(status, out, err, "not finite", "float64")
    assert "--dtype float64" not in err


def test_existing_file_as_output_names_the_option(tmp_path, capsys):
    (tmp_path / "results.txt").write_text("keep me")
    status, out, err = _run(
        _simulate(tmp_path)[:-2] + ["--output", tmp_path / "results.txt"], capsys
    )
    _assert_one_line_error(status, out, err, "--output", "results.txt", "not a directory")
    assert (tmp_path / "results.txt").read_text() == "keep me"


@pytest.mark.parametrize(
    "command, option, values",
    [
        ("simulate", "--seed", ("10", "12")),
        ("simulate", "--dt", ("0.1", "0.2")),
        ("demo", "--steps", ("5", "6")),
        ("fit", "--model", ("constant", "spline")),
    ],
)
def test_an_option_given_twice_is_an_error_naming_it(tmp_path, capsys, command, option, values):
    """argparse keeps the last of a repeated option silently (`--bodies 10 … --bodies 12` ran 12)."""
    argv = {
        "simulate": _simulate(tmp_path),
        "demo": ["demo", "--output", tmp_path / "demo.png", "--no-progress"],
        "fit": ["fit", tmp_path / "obs.csv"],
    }[command]
    status, out, err = _run([*argv, option, values[0], option, values[1]], capsys)
    _assert_one_line_error(status, out, err, option, "only once", values[0], values[1])
    assert not (tmp_path / "run").exists() and not (tmp_path / "demo.png").exists()


def test_fit_errors_about_the_data_name_the_file(tmp_path, capsys):
    """The library's check of the times' span was printed without the file it came from."""
    _, qs = _observations(3)
    path = _write(tmp_path / "span.csv", _csv_lines([-1e308, 0.0, 1e308], qs))
    status, out, err = _run(["fit", path], capsys)
    _assert_one_line_error(status, out, err, f"{path}: ", "`times` span")


def test_fit_out_of_memory_names_the_file_not_the_ensemble_options(tmp_path, capsys, monkeypatch):
    times, qs = _observations(10)
    path = _write(tmp_path / "obs.csv", _csv_lines(times, qs))

    def fail(*args, **kwargs):
        raise MemoryError()

    monkeypatch.setattr("jaxquat._fitting.fit_angular_velocity", fail)
    status, out, err = _run(["fit", path], capsys)
    _assert_one_line_error(status, out, err, "out of memory", f"fitting {path}")
    assert "--bodies" not in err


def test_a_text_file_too_long_to_be_a_csv_is_refused_before_memory_runs_out(
    tmp_path, capsys, monkeypatch
):
    """`fit /dev/zero` read without end until memory ran out; the reader stops at a limit (1 Gi
    characters; 1,000 here)."""
    monkeypatch.setattr("jaxquat._cli._MAX_TEXT", 1000)
    times, qs = _observations(40)
    path = _write(tmp_path / "long.csv", _csv_lines(times, qs))
    assert len(path.read_text()) > 1000
    status, out, err = _run(["fit", path], capsys)
    _assert_one_line_error(status, out, err, str(path), "longer than 1,000 characters")
    short = _write(tmp_path / "short.csv", _csv_lines(times[:5], qs[:5]))
    status, out, err = _run(["fit", short], capsys)
    assert status == 0 and "omega" in out, err


def test_vector_options_take_values_with_a_leading_minus(tmp_path, capsys):
    """`--omega-mean -1,0,0` failed with argparse's "expected one argument" (a value that starts
    with a minus sign and is not a plain number is taken for an option); `=-1,0,0` worked."""
    from jaxquat._cli import _build_parser, _join_negative_vectors

    argv = ["simulate", "--omega-mean", "-1,0,0.5", "--inertia", "1,2,3", "--steps", "2"]
    args = _build_parser().parse_args(_join_negative_vectors(argv))
    assert args.omega_mean == [-1.0, 0.0, 0.5] and args.inertia == [1.0, 2.0, 3.0]
    assert args.steps == 2
    status, out, err = _run(_simulate(tmp_path, "--omega-mean", "-.5,-1e-1,2"), capsys)
    assert status == 0, err
    # A missing value is still reported as one (the next option is not taken for a vector).
    status, out, err = _run([*_simulate(tmp_path / "x"), "--omega-mean"], capsys)
    _assert_one_line_error(status, out, err, "--omega-mean", "expected one argument")


# --- 12. review of the command line: messages, output, repeated and empty options ------------------


def test_times_must_increase_names_distinguishable_times(tmp_path, capsys):
    """`:g` printed Unix times as "t = 1.7e+09 follows t = 1.7e+09"."""
    rows = ["1700000000.0,1,0,0,0", "1700000000.2,1,0,0,0", "1700000000.1,1,0,0,0"]
    path = _write(tmp_path / "epoch.csv", rows)
    status, out, err = _run(["fit", path], capsys)
    _assert_one_line_error(status, out, err, "line 4", "t = 1700000000.1 follows t = 1700000000.2")


def test_fit_reports_the_time_of_q0(tmp_path, capsys):
    """q0 is the orientation at the first observation time, which the output did not say."""
    times, qs = _observations(20)
    path = _write(tmp_path / "obs.csv", _csv_lines(times + 1700000000.5, qs))
    status, out, err = _run(["fit", path, "--json"], capsys)
    assert status == 0, err
    assert json.loads(out)["t0"] == 1700000000.5
    status, out, err = _run(["fit", path], capsys)
    assert status == 0, err
    assert "at t0 = 1700000000.5 " in out
    status, out, err = _run(["fit", "--help"], capsys)
    assert status == 0 and "t0" in out


def test_bench_output_that_is_a_file_says_it_is_not_a_directory(tmp_path, capsys, monkeypatch):
    def must_not_run():
        raise AssertionError("the suite started despite a bad argument")

    monkeypatch.setattr(_bench, "describe_machine", must_not_run)
    (tmp_path / "afile").write_text("keep me")
    status, out, err = _run(["bench", "--no-huge-pages", "--output", tmp_path / "afile"], capsys)
    _assert_one_line_error(status, out, err, "jaxquat bench: error: --output", "not a directory")
    assert (tmp_path / "afile").read_text() == "keep me"


def test_no_progress_bar_when_stderr_is_not_a_terminal(tmp_path, capsys):
    """The bar's carriage returns went into logs, and the error after them was not on a line of its
    own ("\\rensemble: 0%|…\\r   \\rjaxquat: error: …")."""
    argv = ["simulate", "--bodies", "4", "--steps", "3", "--output", tmp_path / "run"]
    status, out, err = _run([*argv, "--dt", "1e30", "--omega-scale", "1e10"], capsys)
    _assert_one_line_error(status, out, err, "not finite")
    assert err.startswith("jaxquat: error: ") and "\r" not in err


def test_no_progress_bar_in_a_log_file_from_a_real_process(tmp_path):
    log = tmp_path / "log.txt"
    command = [sys.executable, "-m", "jaxquat", "simulate", "--bodies", "4", "--steps", "3"]
    command += ["--dt", "1e30", "--omega-scale", "1e10", "--output", str(tmp_path / "run")]
    with open(log, "w") as stderr:
        status = subprocess.run(command, stderr=stderr, stdout=subprocess.DEVNULL, timeout=300)
    text = log.read_text()
    assert status.returncode == 2, text
    assert text.startswith("jaxquat: error: ") and text.count("\n") == 1 and "\r" not in text


def test_show_progress_only_on_a_terminal(monkeypatch):
    from jaxquat import _cli

    class Terminal:
        def isatty(self):
            return True

    monkeypatch.setattr(sys, "stderr", Terminal())
    assert _cli._show_progress(False) and not _cli._show_progress(True)
    monkeypatch.setattr(sys, "stderr", open(os.devnull, "w"))  # noqa: SIM115 (closed below)
    try:
        assert not _cli._show_progress(False)
    finally:
        sys.stderr.close()


def test_simulate_says_it_replaced_a_previous_ensemble(tmp_path, capsys):
    status, out, err = _run(_simulate(tmp_path), capsys)
    assert status == 0 and "the ensemble that was in" not in out, err
    status, out, err = _run(_simulate(tmp_path), capsys)
    assert status == 0, err
    replaced = [line.split() for line in out.splitlines() if line.split()[0] == "replaced"]
    assert replaced == [["replaced", "the", "ensemble", "that", "was", "in", f"{tmp_path}/run/"]]
    status, out, err = _run(["simulate", "--help"], capsys)
    assert "replaced" in " ".join(out.split())


def test_simulate_output_with_a_trailing_slash_is_printed_once(tmp_path, capsys):
    status, out, err = _run(_simulate(tmp_path)[:-1] + [f"{tmp_path / 'run'}/"], capsys)
    assert status == 0, err
    assert f"{tmp_path / 'run'}/ (" in out and "//" not in out


def test_simulate_index_records_every_option_of_the_run(tmp_path, capsys):
    options = ["--seed", "7", "--omega-mean", "0.5,-1,2", "--omega-scale", "0.25"]
    options += ["--inertia", "1,2,3", "--dt", "0.002", "--save-every", "3", "--chunk-size", "3"]
    status, out, err = _run(_simulate(tmp_path, *options, "--no-statistics"), capsys)
    assert status == 0, err
    run = load_ensemble(tmp_path / "run")["metadata"]["run"]
    expected = dict(bodies=4, steps=3, dt=0.002, seed=7, omega_mean=[0.5, -1.0, 2.0])
    expected.update(omega_scale=0.25, inertia=[1.0, 2.0, 3.0], dtype="float32", save_every=3)
    expected.update(chunk_size=3, statistics=False, method="cf4", frame="body")
    assert {key: run[key] for key in expected} == expected
    assert run["jaxquat_version"] == jaxquat.__version__
    # The same options reproduce the run.
    first = load_ensemble(tmp_path / "run")["final"]
    status, out, err = _run(_simulate(tmp_path / "again", *options, "--no-statistics"), capsys)
    assert status == 0, err
    np.testing.assert_array_equal(load_ensemble(tmp_path / "again" / "run")["final"], first)


def test_the_same_seed_draws_the_same_bodies_in_both_dtypes(tmp_path, capsys):
    """jax.random draws other numbers in float32 and float64: at seed 0 the two dtypes simulated
    different ensembles (median turn 94° against 106°), so their accuracy could not be compared. The
    draws are now made in float32 and cast; the float64 initial states are unit to round-off."""
    finals = {}
    for dtype in ("float32", "float64"):
        options = ["--seed", "3", "--omega-scale", "2", "--dtype", dtype, "--save-every", "3"]
        status, out, err = _run(_simulate(tmp_path / dtype, *options), capsys)
        assert status == 0, err
        finals[dtype] = load_ensemble(tmp_path / dtype / "run")
    q32, q64 = (np.asarray(finals[d]["states"], np.float64) for d in ("float32", "float64"))
    np.testing.assert_allclose(q64, q32, atol=2e-6)
    np.testing.assert_allclose(np.linalg.norm(q64[0], axis=-1), 1.0, atol=1e-15)


def test_load_ensemble_reads_a_directory_without_run_metadata(tmp_path):
    q0 = jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (2, 1))
    simulate_ensemble(q0, jnp.ones((2, 3)), 0.1, 2, path=tmp_path / "old")
    assert "run" not in load_ensemble(tmp_path / "old")["metadata"]
    with pytest.raises(ValueError, match="`metadata`"):
        simulate_ensemble(q0, jnp.ones((2, 3)), 0.1, 2, metadata={"x": object()})


@pytest.mark.parametrize(
    "text, fragments",
    [
        ("[simulate]\nbodies = 4\n\n[extra]\nx = 1\n", ["conf.toml line 4", "table [extra]"]),
        ("[extra]\nx = 1\n[simulate]\nbodies = 4\n", ["conf.toml line 1", "table [extra]"]),
        ("[simulat]\nbodies = 4\n", ["conf.toml line 1", "unknown table [simulat]"]),
        ("# options\nsimulat.bodies = 4\n", ["conf.toml line 2", "unknown table [simulat]"]),
        ("steps = 3\n[simulate]\nbodies = 4\n", ["conf.toml line 1", "'steps' outside [simulate]"]),
    ],
)
def test_toml_tables_are_named_with_their_line(tmp_path, capsys, text, fragments):
    """`[simulate]` beside another table gave "unknown key 'simulate'"; `[simulat]` had no line."""
    config = tmp_path / "conf.toml"
    config.write_text(text)
    status, out, err = _run(
        ["simulate", "--config", config, "--no-progress", "--output", tmp_path / "run"], capsys
    )
    _assert_one_line_error(status, out, err, *fragments)
    assert "'simulate'" not in err


def test_fit_refuses_a_file_too_large_for_the_memory(tmp_path, capsys, monkeypatch):
    """1,000,000 rows took 2.0 GB; a 1 GiB CSV (~15 million rows) more than the machine had, and the
    kernel killed the process without a word."""
    from jaxquat import _cli

    assert _cli.fit_memory_needed(1_000_000) >= 2.0e9
    assert _cli.fit_memory_needed(15_000_000) > 20e9
    assert _cli.fit_memory_needed(200_000, "piecewise_linear") >= 1.42e9
    _cli.check_fit_memory(1_000_000, 3 * 2**30, "f.csv")  # fits
    _cli.check_fit_memory(10**9, None, "f.csv")  # unknown: no check
    with pytest.raises(_cli.CommandLineError, match="out of memory .*fitting f.csv"):
        _cli.check_fit_memory(15_000_000, 16 * 2**30, "f.csv")
    times, qs = _observations(10)
    path = _write(tmp_path / "obs.csv", _csv_lines(times, qs))
    monkeypatch.setattr(_cli, "_memory_available", lambda: _cli.fit_memory_needed(10) - 1)
    status, out, err = _run(["fit", path], capsys)
    _assert_one_line_error(status, out, err, "jaxquat: error: out of memory", f"fitting {path}")
    monkeypatch.setattr(_cli, "_memory_available", lambda: _cli.fit_memory_needed(10))
    status, out, err = _run(["fit", path], capsys)
    assert status == 0, err


def test_simulate_refuses_more_bodies_than_the_memory_holds(tmp_path, capsys, monkeypatch):
    """200,000,000 bodies on a 23 GB machine: the kernel killed the process after 160 s (exit 137,
    nothing on stderr); each body takes at least ~175 B on the CPU."""
    from jaxquat import _cli

    _cli.check_simulate_memory(10_000_000, 3 * 2**30)  # fits (2.0 GB measured)
    _cli.check_simulate_memory(10**12, None)  # unknown: no check
    with pytest.raises(_cli.CommandLineError, match="out of memory .*use fewer --bodies"):
        _cli.check_simulate_memory(200_000_000, 22 * 2**30)
    argv = ["simulate", "--bodies", 100, "--steps", 2, "--no-progress", "--output", tmp_path]
    least = 100 * _cli._SIMULATE_MIN_BYTES_PER_BODY
    monkeypatch.setattr(_cli, "_memory_available", lambda: least - 1)
    status, out, err = _run(argv, capsys)
    _assert_one_line_error(status, out, err, "jaxquat: error: out of memory", "use fewer --bodies")
    monkeypatch.setattr(_cli, "_memory_available", lambda: least)
    status, out, err = _run(argv, capsys)
    assert status == 0, err
    # demo too, before it draws any body (its bodies take more memory).
    monkeypatch.setattr(_cli, "_memory_available", lambda: 100 * _cli._DEMO_MIN_BYTES_PER_BODY - 1)
    demo = ["demo", "--bodies", 100, "--output", tmp_path / "d.png"]
    status, out, err = _run(demo, capsys)
    _assert_one_line_error(status, out, err, "jaxquat: error: out of memory", "use fewer --bodies")
    assert not (tmp_path / "d.png").exists()


def test_demo_out_of_memory_advises_only_its_own_options(tmp_path, capsys, monkeypatch):
    """The advice named --chunk-size and --save-every, which demo does not have."""
    from jaxquat import _cli

    def exhausted(*args, **kwargs):
        raise MemoryError()

    monkeypatch.setattr(_cli, "run_demo", exhausted)
    status, out, err = _run(["demo", "--bodies", 10, "--output", tmp_path / "d.png"], capsys)
    _assert_one_line_error(status, out, err, "out of memory", "use fewer --bodies")
    assert "--chunk-size" not in err and "--save-every" not in err


def test_memory_available_reads_proc_meminfo():
    from jaxquat import _cli

    available = _cli._memory_available()
    assert available is None or available > 0


def test_version_prints_the_version(capsys):
    status, out, err = _run(["--version"], capsys)
    assert status == 0 and out == f"jaxquat {jaxquat.__version__}\n", (out, err)


def test_fit_reads_a_csv_written_by_r(tmp_path, capsys):
    """R's write.csv quotes the header (and some write numbers quoted)."""
    times, qs = _observations(20)
    lines = [",".join(f'"{v}"' for v in line.split(",")) for line in _csv_lines(times, qs)]
    path = tmp_path / "r.csv"
    path.write_text('"t","w","x","y","z"\n' + "\n".join(lines[:10] + _csv_lines(times, qs)[10:]))
    status, out, err = _run(["fit", path, "--json"], capsys)
    assert status == 0, err
    np.testing.assert_allclose(json.loads(out)["omega"], OMEGA, atol=1e-6)


def test_broken_pipe_exits_quietly(tmp_path, capsys, monkeypatch):
    """`jaxquat fit f.csv | head -0` printed "jaxquat: error: Broken pipe"."""
    times, qs = _observations(10)
    path = _write(tmp_path / "obs.csv", _csv_lines(times, qs))

    class Gone:
        def write(self, text):
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self):
            pass

    monkeypatch.setattr(sys, "stdout", Gone())
    status, _, err = _run(["fit", path], capsys)
    assert status == 141 and err == "", err


def test_bench_relaunch_keeps_the_options_before_bench(monkeypatch, capsys):
    """The relaunch with huge pages ran `-m jaxquat bench …`, dropping `--distributed`."""
    calls = []
    fake = types.ModuleType("jaxquat._bench")
    fake.relaunch_with_huge_pages = lambda command: calls.append(list(command))
    fake.main = lambda argv: 0
    fake.will_run = lambda argv: True
    monkeypatch.setitem(sys.modules, "jaxquat._bench", fake)
    monkeypatch.setattr("jax.distributed.initialize", lambda: calls.append("initialize"))
    from jaxquat import _cli

    args = _cli._build_parser().parse_args(["--distributed", "bench"])
    args.bench_args, args.global_args, args.from_command_line = ["--quiet"], ["--distributed"], True
    assert _cli._cmd_bench(args) == 0
    assert calls == [["-m", "jaxquat", "--distributed", "bench", "--quiet"], "initialize"]


def test_distributed_without_a_cluster_says_where_it_works(monkeypatch, capsys):
    """`jaxquat --distributed simulate` on a plain host printed only JAX's "coordinator_address
    should be defined." (helper-76): the option relies on JAX finding the other processes itself.
    The line now says so and what to do instead."""

    def initialize():
        raise ValueError("coordinator_address should be defined.")

    monkeypatch.setattr("jax.distributed.initialize", initialize)
    status, _, err = _run(["--distributed", "simulate", "--bodies", "4", "--steps", "2"], capsys)
    assert status == 2 and err.count("\n") == 1, err
    assert "jax.distributed.initialize() failed (coordinator_address should be defined.)" in err
    assert "only under SLURM, Open MPI, Kubernetes or a Cloud TPU" in err


def test_demo_output_that_cannot_be_created_fails_before_the_run(tmp_path, capsys, monkeypatch):
    """A dangling symbolic link passed the directory checks and failed only when the PNG was saved,
    after the whole demo had run and printed its table (a review); the path is now opened first."""

    def must_not_run(*args, **kwargs):
        raise AssertionError("the demo ran before its output was checked")

    monkeypatch.setattr("jaxquat._cli._demo_ensemble", must_not_run)
    link = tmp_path / "link.png"
    link.symlink_to(tmp_path / "missing" / "target.png")
    status, out, err = _run(["demo", "--output", link, "--no-progress"], capsys)
    _assert_one_line_error(status, out, err, "--output", "link.png", "No such file or directory")


def test_demo_output_probe_leaves_files_as_they_were(tmp_path):
    """The probe creates a missing file only for a moment, and leaves an existing one untouched."""
    from jaxquat._cli import _check_png_path

    new = tmp_path / "new.png"
    assert _check_png_path(str(new)) == str(new) and not new.exists()
    old = tmp_path / "old.png"
    old.write_bytes(b"\x89PNG previous figure")
    assert _check_png_path(str(old)) == str(old) and old.read_bytes() == b"\x89PNG previous figure"
    link = tmp_path / "link.png"
    link.symlink_to(tmp_path / "target.png")
    assert _check_png_path(str(link)) == str(link)
    assert link.is_symlink() and not (tmp_path / "target.png").exists()


def test_load_ensemble_reads_an_index_saved_with_a_byte_order_mark(run, tmp_path):
    """An index.json an editor saved again with a UTF-8 byte-order mark loads as before (it was
    "not valid JSON", while the CLI's CSV and TOML readers accept a BOM), and a run writing into
    that directory again can replace it."""
    before = load_ensemble(run)
    text = (run / "index.json").read_text(encoding="utf-8")
    (run / "index.json").write_text("\ufeff" + text, encoding="utf-8")
    after = load_ensemble(run)
    np.testing.assert_array_equal(after["final"], before["final"])
    np.testing.assert_array_equal(after["states"], before["states"])
    simulate_ensemble(np.tile([1.0, 0, 0, 0], (5, 1)), np.ones((5, 3)), 0.1, 2, path=run)
    assert load_ensemble(run)["steps_done"] == 2


@pytest.mark.parametrize("platform", ["cuda", "no-such-platform"])
def test_a_backend_that_cannot_start_is_one_line(tmp_path, platform):
    # jax 0.10 with JAX_PLATFORMS=cuda and no CUDA plugin raises an AssertionError with no message
    # from its first array, which the command line printed as "internal error: AssertionError: ".
    if platform == "cuda" and importlib.util.find_spec("jax_cuda12_plugin") is not None:
        pytest.skip("a CUDA plugin is installed: the backend may start")
    env = {**os.environ, "JAX_PLATFORMS": platform}
    command = [sys.executable, "-m", "jaxquat", "simulate", "--bodies", "4", "--steps", "3"]
    command += ["--output", str(tmp_path / "run")]
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 2, done
    _assert_one_line_error(2, done.stdout, done.stderr, f"JAX_PLATFORMS={platform!r}")
    assert "could not start" in done.stderr and "AssertionError: \n" not in done.stderr
    assert not (tmp_path / "run").exists()
    # The suite's --help and its argument errors need no backend (they printed the backend's error).
    bench = [sys.executable, "-m", "jaxquat", "bench", "--no-huge-pages"]
    done = subprocess.run([*bench, "--help"], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0 and done.stdout.startswith("usage: jaxquat bench"), done
    assert done.stdout.count("usage:") == 1 and done.stderr == "", done
    done = subprocess.run(
        [*bench, "--preset", "x"], capture_output=True, text=True, env=env, timeout=300
    )
    _assert_one_line_error(2, done.stdout, done.stderr, "argument --preset: invalid choice")
    # ... nor do the checks made after parsing (they too printed the backend's error).
    (tmp_path / "a_file").write_text("")
    for arguments, message in [
        (["--workloads", "W9"], "unknown workload(s) W9"),
        (["--dtypes", "float16"], "--dtypes must be float64 and/or float32"),
        (["--output", str(tmp_path / "a_file")], "exists and is not a directory"),
        (["--output", str(tmp_path / "a_file" / "sub")], "a_file is not a directory"),
    ]:
        done = subprocess.run(
            [*bench, *arguments], capture_output=True, text=True, env=env, timeout=300
        )
        _assert_one_line_error(2, done.stdout, done.stderr, message)
    output = ["--output", str(tmp_path / "bench")]
    done = subprocess.run([*bench, *output], capture_output=True, text=True, env=env, timeout=300)
    _assert_one_line_error(2, done.stdout, done.stderr, f"JAX_PLATFORMS={platform!r}")
