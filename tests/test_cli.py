"""Tests for the command line: one-line errors with exit 2, fit recovers ω, simulate writes, demo runs."""

import json
import os
import re
import signal
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxquat
from jaxquat._cli import main

OMEGA = np.array([0.4, -0.25, 0.7])


def _observations(count=40, noise=0.0, seed=0):
    """Orientations of a body turning at the constant rate OMEGA (world frame), with optional noise."""
    times = np.linspace(0.0, 6.0, count)
    q_start = jaxquat.from_rotvec(jnp.array([0.3, -1.2, 0.5]))
    qs = jaxquat.multiply(jaxquat.from_rotvec(times[:, None] * OMEGA), q_start)
    if noise:
        perturbation = noise * jax.random.normal(jax.random.key(seed), (count, 3))
        qs = jaxquat.multiply(jaxquat.from_rotvec(perturbation), qs)
    return times, np.array(qs)


def _write_csv(path, times, qs, header=True):
    lines = ["t,w,x,y,z"] if header else []
    lines += [",".join(repr(float(v)) for v in (t, *q)) for t, q in zip(times, qs, strict=True)]
    path.write_text("\n".join(lines) + "\n")
    return path


def _run(argv, capsys):
    status = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def _assert_one_line_error(status, err, *fragments):
    assert status == 2, err
    assert err.endswith("\n") and err.count("\n") == 1, repr(err)
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in err, (fragment, err)


def test_fit_recovers_omega_from_a_generated_csv(tmp_path, capsys):
    times, qs = _observations(noise=1e-4)
    qs[::3] *= -1  # the sign of a quaternion does not matter
    path = _write_csv(tmp_path / "obs.csv", times, qs)
    status, out, err = _run(["fit", path, "--json"], capsys)
    assert status == 0, err
    report = json.loads(out)
    assert np.linalg.norm(np.array(report["omega"]) - OMEGA) < 1e-4
    assert report["converged"] and report["observations"] == 40
    assert report["residual_rms_deg"] < 0.02
    # Without a header, plain text output; exact data give ω to round-off.
    times, qs = _observations()
    path = _write_csv(tmp_path / "exact.csv", times, qs, header=False)
    status, out, err = _run(["fit", path], capsys)
    assert status == 0, err
    printed = out.split("[", 1)[1].split("]", 1)[0]
    np.testing.assert_allclose([float(v) for v in printed.split(",")], OMEGA, atol=1e-8)
    # The first time is printed as the file writes it: "0.0" here (`repr`), "0" below (it read
    # `t0 = 0.0` for a file writing 0, where a file writing 5 read `t0 = 5`).
    assert times[0] == 0 and "at t0 = 0.0 (the first observation)" in out, out
    lines = path.read_text().splitlines()
    path.write_text("\n".join(["0" + lines[0][len("0.0") :], *lines[1:]]) + "\n")
    status, out, err = _run(["fit", path], capsys)
    assert status == 0, err
    assert "at t0 = 0 (the first observation)" in out, out


def test_fit_reads_a_csv_with_a_byte_order_mark_and_crlf_line_ends(tmp_path, capsys):
    # Spreadsheet exports: UTF-8 with a BOM before the header, Windows line ends. Same ω as plain.
    times, qs = _observations()
    plain = _write_csv(tmp_path / "plain.csv", times, qs)
    exported = tmp_path / "exported.csv"
    exported.write_bytes(b"\xef\xbb\xbf" + plain.read_text().replace("\n", "\r\n").encode())
    reports = []
    for path in (plain, exported):
        status, out, err = _run(["fit", path, "--json"], capsys)
        assert status == 0, err
        reports.append(json.loads(out))
    np.testing.assert_allclose(reports[1]["omega"], reports[0]["omega"], rtol=0, atol=0)
    np.testing.assert_allclose(reports[1]["omega"], OMEGA, atol=1e-8)


def _csv_cases(tmp_path):
    times, qs = _observations(count=6)
    good = [",".join(repr(float(v)) for v in (t, *q)) for t, q in zip(times, qs, strict=True)]

    def write(name, lines):
        path = tmp_path / name
        path.write_text("\n".join(lines) + "\n")
        return path

    bad_time = good[:3] + [good[1]] + good[4:]
    return [
        (["fit", tmp_path / "missing.csv"], ["missing.csv", "no such file"]),
        (["fit", write("empty.csv", [])], ["empty.csv", "empty"]),
        (["fit", write("header_only.csv", ["t,w,x,y,z"])], ["no data rows"]),
        (
            ["fit", write("columns.csv", ["t,w,x,y,z"] + good[:2] + [good[2].rsplit(",", 1)[0]])],
            ["line 4", "5 columns"],
        ),
        (
            ["fit", write("text.csv", good[:1] + [good[1].replace(good[1].split(",")[2], "abc")])],
            ["line 2", "column x", "abc"],
        ),
        (
            [
                "fit",
                write(
                    "nan.csv", good[:4] + [good[4].replace(good[4].split(",")[1], "nan")] + good[5:]
                ),
            ],
            ["line 5", "column w", "not finite"],
        ),
        (["fit", write("order.csv", ["t,w,x,y,z"] + bad_time)], ["line 5", "times must increase"]),
        (["fit", write("few.csv", good[:2])], ["at least 3"]),
        (["fit", write("header.csv", ["time,qw,qx,qy,qz"] + good)], ["line 1", "header"]),
        (["fit", write("zero.csv", good[:2] + ["9.0,0,0,0,0"])], ["line 3", "zero"]),
        (["fit", tmp_path], ["is a directory"]),
    ]


def test_malformed_inputs_give_one_line_and_exit_2(tmp_path, capsys):
    config_bad_syntax = tmp_path / "syntax.toml"
    config_bad_syntax.write_text("bodies = 10\nsteps = = 3\n")
    config_unknown = tmp_path / "unknown.toml"
    config_unknown.write_text("bodies = 10\n\nspeed = 3\n")
    config_bad_value = tmp_path / "value.toml"
    config_bad_value.write_text("# an ensemble\nbodies = -4\n")
    config_bad_type = tmp_path / "type.toml"
    config_bad_type.write_text('dt = "fast"\n')
    cases = _csv_cases(tmp_path) + [
        ([], ["required"]),
        (["teleport"], ["invalid choice"]),
        (["simulate", "--bodies", "-5"], ["--bodies", "positive integer"]),
        (["simulate", "--dt", "nan"], ["--dt", "finite"]),
        (["simulate", "--inertia", "1,2"], ["--inertia", "three"]),
        (
            [
                "simulate",
                "--bodies",
                "4",
                "--steps",
                "2",
                "--method",
                "heun",
                "--no-progress",
                "--output",
                tmp_path / "out",
            ],
            ["method", "heun"],
        ),
        (["simulate", "--config", tmp_path / "nope.toml"], ["nope.toml", "no such file"]),
        (["simulate", "--config", config_bad_syntax], ["syntax.toml", "invalid TOML", "line 2"]),
        (["simulate", "--config", config_unknown], ["unknown.toml line 3", "speed"]),
        (["simulate", "--config", config_bad_value], ["value.toml line 2", "bodies"]),
        (["simulate", "--config", config_bad_type], ["type.toml line 1", "dt"]),
        (["demo", "--output", tmp_path / "no" / "such" / "dir.png"], ["does not exist"]),
        (["demo", "--output", tmp_path / "figure.jpg"], [".png"]),
        (["fit", "--model", "cubic", "x.csv"], ["--model", "cubic"]),
    ]
    assert len(cases) >= 10
    for argv, fragments in cases:
        status, out, err = _run(argv, capsys)
        _assert_one_line_error(status, err, *fragments)
        assert out == "", (argv, out)


def test_unexpected_errors_are_one_line_too(monkeypatch, capsys):
    def broken(args):
        raise RuntimeError("something\nbroke")

    monkeypatch.setattr("jaxquat._cli._cmd_bench", broken)
    status, out, err = _run(["bench"], capsys)
    assert status == 1 and err == "jaxquat: internal error: RuntimeError: something broke\n"


def test_bench_without_the_suite_is_a_one_line_error(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "jaxquat._bench", None)  # makes the import fail
    status, out, err = _run(["bench"], capsys)
    _assert_one_line_error(status, err, "benchmark suite")


def test_bench_passes_its_arguments_to_the_suite(monkeypatch, capsys):
    calls = []
    fake = type(sys)("jaxquat._bench")
    fake.main = lambda argv: calls.append(argv) or 0
    fake.will_run = lambda argv: True
    monkeypatch.setitem(sys.modules, "jaxquat._bench", fake)
    monkeypatch.setattr(jaxquat, "_bench", fake, raising=False)
    status, _, err = _run(["bench", "--workloads", "W1"], capsys)
    assert status == 0, err
    assert calls == [["--workloads", "W1"]]
    # A --preset of the user's reaches the suite once (a review: the command put "--preset quick"
    # first, so every --preset, quick included, was a "given only once" error).
    for preset in ["quick", "full", "micro"]:
        status, _, err = _run(["bench", "--preset", preset, "--output", "out"], capsys)
        assert status == 0, err
        assert calls[-1] == ["--preset", preset, "--output", "out"]


def test_bench_without_a_preset_runs_the_quick_one():
    from jaxquat import _bench

    assert _bench._parse([]).preset == "quick"
    assert _bench._parse(["--preset", "micro"]).preset == "micro"


def test_bench_will_run_is_quiet_and_false_for_help_and_bad_arguments(capsys):
    from jaxquat import _bench

    assert _bench.will_run([]) and _bench.will_run(["--workloads", "W1", "--preset", "micro"])
    assert not _bench.will_run(["--help"]) and not _bench.will_run(["--preset", "x"])
    assert not _bench.will_run(["--repeats", "0"])
    # The checks made after parsing count too (the backend started before their one-line errors).
    assert not _bench.will_run(["--workloads", "W9"]) and not _bench.will_run(["--workloads", ""])
    assert not _bench.will_run(["--workloads", "W1,w1"])
    assert not _bench.will_run(["--dtypes", "float16"])
    assert not _bench.will_run(["--output", __file__])
    assert not _bench.will_run(["--output", os.path.join(__file__, "sub", "dir")])
    assert capsys.readouterr() == ("", "")


def test_bench_output_that_cannot_be_made_is_named_before_anything_runs(tmp_path, monkeypatch):
    """An `--output` under a file, or in a directory this user may not write into, was found only
    by `main` after JAX's backend had started. Nothing is created by the check."""
    from jaxquat import _bench

    (tmp_path / "a_file").write_text("")
    with pytest.raises(ValueError, match=r"--output .*a_file is not a directory"):
        _bench._check_creatable(tmp_path / "a_file" / "x" / "y")
    target = tmp_path / "new" / "results"
    _bench._check_creatable(target)  # creatable: no error, and nothing made
    assert not (tmp_path / "new").exists()
    _bench._check_creatable(tmp_path)  # (exists already)
    # (The tests may run as root, for whom every directory is writable: the answer is simulated.)
    monkeypatch.setattr(_bench.os, "access", lambda path, mode: False)
    with pytest.raises(ValueError, match=r"no permission to create it in .*"):
        _bench._check_creatable(target)
    assert not _bench.will_run(["--output", str(target)])


def test_help_exits_0(capsys):
    status, out, _ = _run(["--help"], capsys)
    assert status == 0 and "simulate" in out


def test_simulate_from_toml_writes_a_readable_ensemble(tmp_path, capsys):
    config = tmp_path / "run.toml"
    output = tmp_path / "ensemble"
    config.write_text(
        f"bodies = 300\nsteps = 40\ndt = 0.05\nomega_mean = [0.0, 0.0, 1.0]\nomega_scale = 0.0\n"
        f'save_every = 10\nchunk_size = 20\noutput = "{output}"\n'
    )
    status, out, err = _run(
        ["simulate", "--config", config, "--steps", "60", "--no-progress"], capsys
    )
    assert status == 0, err
    assert "300 kinematic bodies, 60 steps" in out and "throughput" in out
    assert "(7 states (every 10 steps, steps 0 to 60) and the final state;" in out
    # 18,000 body-steps in about a second (compile included): three significant figures, not "0.0 M".
    rate = re.search(r"throughput\s+([0-9.]+) ([kMG]?) ?body-steps/s", out)
    assert rate is not None, out
    assert float(rate.group(1)) > 0 and len(rate.group(1).replace(".", "").lstrip("0")) >= 2
    data = jaxquat.load_ensemble(output)
    assert data["complete"] and data["states"].shape == (7, 300, 4)
    # Every body turns about z at 1 rad/s: 3 rad after 60 steps of 0.05 s.
    np.testing.assert_allclose(data["total_angle"], 3.0, rtol=1e-5)
    turned = jaxquat.multiply(jaxquat.from_rotvec(jnp.array([0.0, 0.0, 3.0])), data["states"][0])
    np.testing.assert_allclose(
        np.abs(np.sum(np.asarray(turned) * data["final"], -1)), 1.0, atol=1e-5
    )


def test_simulate_rigid_bodies_from_options(tmp_path, capsys):
    status, out, err = _run(
        [
            "simulate",
            "--bodies",
            "50",
            "--steps",
            "20",
            "--inertia",
            "1,2,3",
            "--dtype",
            "float64",
            "--no-statistics",
            "--no-progress",
            "--output",
            tmp_path / "rigid",
        ],
        capsys,
    )
    assert status == 0, err
    assert "rigid bodies" in out and "cf4 / body / float64" in out
    assert "(final state;" in out
    data = jaxquat.load_ensemble(tmp_path / "rigid")
    assert data["final"].dtype == np.float64 and "total_angle" not in data


def _cli(*argv, cwd, timeout=600):
    env = dict(os.environ, MPLBACKEND="Agg", JAX_PLATFORMS="cpu", JAX_NUMPY_RANK_PROMOTION="raise")
    return subprocess.run(
        [sys.executable, "-m", "jaxquat", *map(str, argv)],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=timeout,
    )


def test_python_m_jaxquat_demo_writes_its_png(tmp_path):
    proc = _cli("demo", "--bodies", "20000", "--no-progress", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    png = tmp_path / "jaxquat_demo.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "attitude spread" in proc.stdout and "fitted ω" in proc.stdout
    assert "converged: True" in proc.stdout


def test_python_m_jaxquat_bad_file_in_a_real_process(tmp_path):
    (tmp_path / "bad.csv").write_text("t,w,x,y,z\n0,1,0,0,0\n1,1,0,0\n")
    proc = _cli("fit", "bad.csv", cwd=tmp_path)
    assert proc.returncode == 2
    assert (
        proc.stderr == "jaxquat fit: error: bad.csv line 3: expected 5 columns (t,w,x,y,z), got 4\n"
        or (proc.stderr.count("\n") == 1 and "line 3" in proc.stderr)
    )
    assert proc.stdout == ""


@pytest.mark.parametrize("argv", [["fit", "x.csv", "--bogus"], ["demo", "--bodies", "3", "extra"]])
def test_unknown_global_option(argv, capsys):
    status, _, err = _run(argv, capsys)
    _assert_one_line_error(status, err, "unrecognized arguments")


@pytest.mark.parametrize(
    "options, saved",
    [
        (["--save-every", "2"], "holds 3 saved states, steps 0 to 4 (jaxquat.load_ensemble"),
        # Without --save-every nothing but the index is written before the end of the run.
        ([], "holds no saved states (without --save-every only the final state is saved"),
    ],
)
def test_interrupted_simulate_says_what_it_saved(monkeypatch, tmp_path, capsys, options, saved):
    real = jaxquat._ensemble.simulate_ensemble

    def interrupted_after_two_chunks(*args, **kwargs):
        def progress(done, total):
            if done >= 4:
                raise KeyboardInterrupt

        return real(*args, **dict(kwargs, progress=progress))

    monkeypatch.setattr("jaxquat._ensemble.simulate_ensemble", interrupted_after_two_chunks)
    argv = ["simulate", "--bodies", "3", "--steps", "10", "--chunk-size", "2", *options]
    status, out, err = _run([*argv, "--output", tmp_path / "run"], capsys)
    assert status == 130 and err.count("\n") == 1, err
    assert err.startswith("jaxquat: interrupted after 4 of 10 steps; ") and saved in err, err
    assert f"{tmp_path / 'run'}/ holds" in err
    data = jaxquat.load_ensemble(tmp_path / "run")
    assert data["steps"].tolist() == ([0, 2, 4] if options else []) and data["steps_done"] == 4


def test_interrupted_before_writing_says_nothing_of_the_output(monkeypatch, tmp_path, capsys):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("jaxquat._ensemble.simulate_ensemble", interrupted)
    status, out, err = _run(
        ["simulate", "--bodies", "3", "--steps", "2", "--output", tmp_path / "run"], capsys
    )
    assert status == 130 and err == "jaxquat: interrupted\n"


# Run as `python -m jaxquat` (main() without arguments), with Ctrl-C as in a terminal. The crash after
# Ctrl-C (exit -11 instead of 130) was in the interpreter's teardown, with XLA still running: the
# process must end right after its one line, so a handler registered with atexit must not run.
_AS_THE_COMMAND_LINE = """
import atexit, runpy, signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)
atexit.register(lambda: print("interpreter teardown", file=sys.stderr))
{setup}
sys.argv = ["jaxquat", *{argv!r}]
runpy.run_module("jaxquat", run_name="__main__")
"""


def _start(argv, cwd, setup=""):
    script = _AS_THE_COMMAND_LINE.format(setup=setup, argv=[str(a) for a in argv])
    return subprocess.Popen(
        [sys.executable, "-c", script],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
    )


def _steps_done(run):
    try:
        return json.loads((run / "index.json").read_text())["steps_done"]
    except (OSError, ValueError):  # not written yet
        return 0


def test_ctrl_c_during_a_streaming_run_ends_the_process_after_one_line(tmp_path):
    run = tmp_path / "run"
    argv = ["simulate", "--bodies", "1000", "--steps", "2000000000", "--save-every", "10000"]
    process = _start([*argv, "--chunk-size", "10000", "--no-progress", "--output", run], tmp_path)
    deadline = time.monotonic() + 300
    while process.poll() is None and _steps_done(run) == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    process.send_signal(signal.SIGINT)
    out, err = process.communicate(timeout=300)
    assert process.returncode == 130 and err.count("\n") == 1, (process.returncode, err)
    assert err.startswith("jaxquat: interrupted after ") and out == "", err
    data = jaxquat.load_ensemble(run)  # what the line says is there, all of it on disk
    assert not data["complete"] and f"holds {len(data['steps']):,} saved states" in err, err


# Ctrl-C that lands in a callback Python cannot raise from (JAX's garbage-collection callback, a
# __del__) was only reported ("Exception ignored in: ...", a traceback), and the command ran on to
# exit 0 (a probe hit it in 1 of 10–45 tries). Here a __del__ raises it, deterministically.
_SWALLOWED_INTERRUPT = """
import jaxquat._cli
setup_jax = jaxquat._cli._setup_jax
class Swallowed:
    def __del__(self):
        raise KeyboardInterrupt
def interrupted_in_a_callback(dtype):
    Swallowed()  # destroyed at once: its __del__'s KeyboardInterrupt is unraisable
    return setup_jax(dtype)
jaxquat._cli._setup_jax = interrupted_in_a_callback
"""


def test_ctrl_c_in_a_callback_python_cannot_raise_from_still_interrupts(tmp_path):
    argv = ["simulate", "--bodies", "3", "--steps", "2", "--output", tmp_path / "run"]
    process = _start(argv, tmp_path, setup=_SWALLOWED_INTERRUPT)
    out, err = process.communicate(timeout=300)
    assert (process.returncode, err, out) == (130, "jaxquat: interrupted\n", "")
    assert not (tmp_path / "run").exists()


_INTERRUPTED_STARTING = {
    # Ctrl-C while main() sets up (importing and configuring jax, compiling): its own line.
    "main": "import jaxquat._cli\n"
    "def interrupted(dtype):\n"
    "    raise KeyboardInterrupt\n"
    "jaxquat._cli._setup_jax = interrupted\n",
    # Ctrl-C while `python -m jaxquat` loads the command line module, before main() runs.
    "loading": "class Interrupted:\n"
    "    def find_spec(self, name, path=None, target=None):\n"
    "        if name == 'jaxquat._cli':\n"
    "            raise KeyboardInterrupt\n"
    "sys.meta_path.insert(0, Interrupted())\n",
}


@pytest.mark.parametrize("when", sorted(_INTERRUPTED_STARTING))
def test_ctrl_c_while_starting_is_one_line_and_130(tmp_path, when):
    argv = ["simulate", "--bodies", "3", "--steps", "2", "--output", tmp_path / "run"]
    process = _start(argv, tmp_path, setup=_INTERRUPTED_STARTING[when])
    out, err = process.communicate(timeout=300)
    assert (process.returncode, err, out) == (130, "jaxquat: interrupted\n", "")


def test_simulate_into_an_unwritable_output_is_one_line_error(tmp_path, capsys):
    # An output directory that cannot be created (its parent is a file): the OS's reason, exit 2.
    (tmp_path / "file").write_text("x")
    target = tmp_path / "file" / "run"
    argv = ["simulate", "--bodies", "4", "--steps", "2", "--save-every", "1", "--output", target]
    status, out, err = _run([*argv, "--no-progress"], capsys)
    _assert_one_line_error(status, err, str(target))
    assert "internal error" not in err


# Ctrl-C while `python -m jaxquat` imports the package itself (jax takes about a second to load),
# before __main__ exists to catch it: a real SIGINT, sent when the package first imports jax. This once
# printed a traceback through runpy.
_SIGINT_ON_IMPORTING_JAX = """
import os, signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal (xdist ignores SIGINT)
class SignalOnJax:
    def find_spec(self, name, path=None, target=None):
        if name == "jax":
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)
sys.meta_path.insert(0, SignalOnJax())
"""


def test_ctrl_c_while_python_m_jaxquat_imports_the_package_is_one_line_and_130(tmp_path):
    (tmp_path / "sitecustomize.py").write_text(_SIGINT_ON_IMPORTING_JAX)
    path = os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    process = subprocess.run(
        [sys.executable, "-m", "jaxquat", "demo", "--help"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=dict(os.environ, PYTHONPATH=path, JAX_PLATFORMS="cpu"),
        timeout=300,
    )
    assert (process.returncode, process.stderr, process.stdout) == (
        130,
        "jaxquat: interrupted\n",
        "",
    )


def test_importing_jaxquat_as_a_library_keeps_the_sigint_handler(tmp_path):
    """Only `python -m jaxquat` handles Ctrl-C while loading; a program importing jaxquat keeps its
    KeyboardInterrupt, and its own handler is left alone."""
    script = (
        "import signal, sys\n"
        "mine = lambda *a: None\n"
        "signal.signal(signal.SIGINT, mine)\n"
        "import jaxquat\n"
        "assert signal.getsignal(signal.SIGINT) is mine\n"
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "sys.argv = ['-m']\n"  # as while `python -m jaxquat` loads the package
        "import importlib, jaxquat\n"
        "importlib.reload(jaxquat)\n"
        "assert signal.getsignal(signal.SIGINT) is signal.default_int_handler\n"
        "print('ok')\n"
    )
    process = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path, timeout=300
    )
    assert process.stdout == "ok\n", process.stderr


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
@pytest.mark.parametrize("argv", [["--help"], ["--version"], ["simulate", "--help"]])
def test_help_into_a_full_device_is_an_error(tmp_path, argv):
    """argparse ignores a failed write of its help: `--help > /dev/full` exited 0 with nothing."""
    with open("/dev/full", "w") as full:
        proc = subprocess.run(
            [sys.executable, "-m", "jaxquat", *argv],
            stdout=full,
            stderr=subprocess.PIPE,
            text=True,
            cwd=tmp_path,
            env=dict(os.environ, JAX_PLATFORMS="cpu"),
            timeout=300,
        )
    assert (proc.returncode, proc.stderr) == (2, "jaxquat: error: No space left on device\n")


def test_fit_with_stdout_closed_is_an_error(tmp_path):
    """Started with stdout closed (`>&-`), print() drops everything: the fit's result was lost and
    the command exited 0."""
    times = np.linspace(0.0, 1.0, 11)
    _write_csv(tmp_path / "obs.csv", times, jaxquat.step(jaxquat.identity(), jnp.ones(3), times))
    proc = subprocess.run(  # (a shell closes stdout: preexec_fn would fork this JAX process)
        ["sh", "-c", 'exec "$0" -m jaxquat fit obs.csv --json >&-', sys.executable],
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
        timeout=300,
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr == (
        "jaxquat: error: standard output is closed: there is nowhere to write the fit\n"
    )


def test_a_stdout_that_cannot_encode_the_summary_does_not_fail_the_run(tmp_path):
    """`simulate` under PYTHONIOENCODING=ascii (a Windows redirect in cp1252 alike) wrote its
    ensemble, then died on the summary's '°' with exit 2, reported as bad input (helper-49).
    The characters print as '?' and the run exits 0."""
    argv = ["simulate", "--bodies", "2", "--steps", "2", "--no-progress"]
    done = subprocess.run(
        [sys.executable, "-m", "jaxquat", *argv, "--output", str(tmp_path / "run")],
        capture_output=True,
        env=dict(os.environ, JAX_PLATFORMS="cpu", PYTHONIOENCODING="ascii"),
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert b"angle from start" in done.stdout and b"?" in done.stdout and done.stderr == b""
    assert jaxquat.load_ensemble(tmp_path / "run")["final"].shape == (2, 4)


@pytest.mark.parametrize(
    "steps, every, saved",
    [
        (7, 50, "1 state (every 50 steps, steps 0 to 0)"),
        (7, 3, "3 states (every 3 steps, steps 0 to 6)"),
        (2, 1, "3 states (every step, steps 0 to 2)"),
    ],
)
def test_simulate_says_which_steps_it_saved(tmp_path, capsys, steps, every, saved):
    """The summary said "states every 50 steps" for a run of 7 steps, which saves step 0 alone (a
    review): the saved steps are 0, k, 2k, …, and the last step only when k divides the steps."""
    argv = ["simulate", "--bodies", "3", "--steps", str(steps), "--save-every", str(every)]
    status, out, err = _run([*argv, "--no-progress", "--output", tmp_path / "run"], capsys)
    assert status == 0, err
    assert f"({saved} and the final state;" in out
    data = jaxquat.load_ensemble(tmp_path / "run")
    assert data["states"].shape[0] == int(saved.split()[0])
