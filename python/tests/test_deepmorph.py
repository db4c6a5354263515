"""Tests of the Python module against the program and the library's own numbers.

The CLI comparison runs the `deepmorph` binary of the Rust test build
(`target/debug/deepmorph`, or `DEEPMORPH_BIN`). The deep morph needs the team's shared data
(`../shared/data`); with `DEEPMORPH_REQUIRE_SHARED_DATA=1` (CI) its absence is a failure.
"""

import json
import os
import signal
import struct
import subprocess
import threading
import time
import zlib
from pathlib import Path

import numpy as np
import pytest

import deepmorph

REPO = Path(__file__).resolve().parents[2]
SHARED_DATA = REPO.parent / "shared" / "data"
# A quick morph: 32x32, 3 steps, 2 levels x 6 sweeps.
QUICK = dict(K=3, levels=2, sweeps=6, size=(32, 32))


def disc(centre, radius=6.0, side=32, colour=(1.0, 0.5, 0.2)):
    """A smooth coloured disc on black, float32 [side, side, 3]."""
    yy, xx = np.mgrid[0:side, 0:side].astype(np.float32)
    r = np.hypot(yy - centre[0], xx - centre[1])
    alpha = np.clip(radius + 1.0 - r, 0.0, 1.0)[..., None]
    return (alpha * np.asarray(colour, np.float32)).astype(np.float32)


@pytest.fixture(scope="module")
def pair():
    return disc((14, 13)), disc((17, 19))


@pytest.fixture(scope="module")
def quick(pair):
    return deepmorph.morph(*pair, **QUICK)


def cli_binary():
    path = Path(os.environ.get("DEEPMORPH_BIN", REPO / "target" / "debug" / "deepmorph"))
    if not path.is_file():
        pytest.fail(f"{path} not found: build the program first (cargo build) or set DEEPMORPH_BIN")
    return path


def write_png(path, image):
    """`image` (float, [H, W, 3]) as an 8-bit RGB PNG, without an imaging library."""
    pixels = np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)
    h, w, _ = pixels.shape
    rows = b"".join(b"\x00" + pixels[i].tobytes() for i in range(h))

    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows))
        + chunk(b"IEND", b"")
    )


def test_shapes_dtypes_and_endpoints(quick, pair):
    a, b = pair
    k, h, w = 3, 32, 32
    assert quick.frames.shape == (k + 1, h, w, 3) and quick.frames.dtype == np.float32
    assert quick.deformations.shape == (k, 2, h, w) and quick.deformations.dtype == np.float32
    assert quick.composed.shape == (2, h, w) and quick.composed.dtype == np.float32
    # The endpoints are the inputs (SPEC: u_0 = A, u_K = B), bit for bit for float32 inputs.
    np.testing.assert_array_equal(quick.frames[0], a)
    np.testing.assert_array_equal(quick.frames[-1], b)
    # The identity lies on the boundary of every deformation (SPEC §2: phi = Id on the border).
    rows = np.arange(h, dtype=np.float32)
    np.testing.assert_allclose(quick.deformations[:, 0, 0, :], 0.0, atol=1e-5)
    np.testing.assert_allclose(quick.deformations[:, 0, :, 0], rows[None, :].repeat(k, 0), atol=1e-5)
    assert quick.termination == "completed"
    energy = quick.energy
    n = len(energy["E"])
    assert n == 2 * (6 + 1)  # sweep 0 and 6 sweeps on each level
    assert all(len(v) == n for v in energy.values())
    assert energy["E"].dtype == np.float64 and np.all(np.isfinite(energy["E"]))
    # Every joint sweep's K = 3 deformation searches try at least once each.
    assert np.all(energy["trials_phi"][energy["sweep"] > 0] >= 3)
    assert quick.config["inputs"] == {"kind": "arrays", "a": [32, 32], "b": [32, 32]}
    assert quick.config["config"]["solver"]["steps"] == 3


def test_arrays_are_read_only_and_own_their_buffers(quick):
    for array in (quick.frames, quick.deformations, quick.composed):
        assert not array.flags.writeable
        assert array.flags.c_contiguous
        # No copy behind the array: NumPy holds the Rust buffer, not a view of another array.
        assert not isinstance(array.base, np.ndarray)
    assert quick.frames is quick.frames


def test_uint8_and_float_inputs_agree(pair):
    a, b = pair
    a8, b8 = (np.round(x * 255).astype(np.uint8) for x in pair)
    from_bytes = deepmorph.morph(a8, b8, **QUICK)
    from_floats = deepmorph.morph(a8 / np.float32(255), b8 / np.float32(255), **QUICK)
    np.testing.assert_array_equal(from_bytes.deformations, from_floats.deformations)


@pytest.mark.parametrize("backend", ["flex", "ndarray"])
def test_same_deformations_and_files_as_the_program(tmp_path, pair, backend):
    a_png, b_png = tmp_path / "a.png", tmp_path / "b.png"
    write_png(a_png, pair[0])
    write_png(b_png, pair[1])
    cli_out = tmp_path / "cli"
    subprocess.run(
        [cli_binary(), "morph", a_png, b_png, "-o", cli_out, "-K", "3", "--levels", "2",
         "--sweeps", "6", "--size", "32x32", "--delta", "0.02", "--backend", backend, "--quiet"],
        check=True,
    )
    m = deepmorph.morph(
        str(a_png), b_png, K=3, levels=2, sweeps=6, size=(32, 32), delta=0.02, backend=backend
    )
    py_out = Path(m.save(tmp_path / "py"))
    assert sorted(p.name for p in py_out.iterdir()) == sorted(p.name for p in cli_out.iterdir())
    shape = json.loads((cli_out / "deformations.json").read_text())["shape"]
    cli_phi = np.fromfile(cli_out / "deformations.f32", dtype="<f4").reshape(shape)
    np.testing.assert_allclose(m.deformations, cli_phi, rtol=0, atol=1e-6)
    py_phi = np.fromfile(py_out / "deformations.f32", dtype="<f4").reshape(shape)
    np.testing.assert_array_equal(py_phi, m.deformations)
    # The same record but for the seconds (the whole solve's, each level's, and the program's
    # time estimate); the same metrics as the file the program wrote.
    cli_config = json.loads((cli_out / "config.json").read_text())
    py_config = json.loads((py_out / "config.json").read_text())
    for record in (cli_config, py_config):
        record["outcome"].pop("seconds")
        record["outcome"].pop("estimate", None)
        for level in record["outcome"]["levels"]:
            level.pop("seconds")
    assert py_config == cli_config
    assert m.config["inputs"]["kind"] == "files"
    cli_metrics = json.loads((cli_out / "metrics.json").read_text())
    assert_same_numbers(m.metrics, cli_metrics)
    # `evaluate` measures the saved folder as `deepmorph eval` does (on the same backend).
    evaluated = deepmorph.evaluate(py_out, backend=backend)
    assert_same_numbers(evaluated, json.loads((py_out / "metrics.json").read_text()))


def assert_same_numbers(got, expected, path="metrics"):
    """Equal structure; numbers equal to 1e-9 relative (the frames and energies are the
    same, the float formatting of a file aside)."""
    if isinstance(expected, dict):
        assert isinstance(got, dict) and got.keys() == expected.keys(), path
        for key in expected:
            assert_same_numbers(got[key], expected[key], f"{path}.{key}")
    elif isinstance(expected, list):
        assert isinstance(got, list) and len(got) == len(expected), path
        for i, (g, e) in enumerate(zip(got, expected)):
            assert_same_numbers(g, e, f"{path}[{i}]")
    elif isinstance(expected, float):
        assert got == pytest.approx(expected, rel=1e-9, abs=1e-12), path
    else:
        assert got == expected, path


def test_saved_morph_is_refused_over_without_force_and_replaced_with_it(tmp_path, quick):
    folder = tmp_path / "out"
    quick.save(folder)
    with pytest.raises(ValueError, match="force"):
        quick.save(folder)
    assert Path(quick.save(folder, force=True)) == folder
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(ValueError):
        quick.save(tmp_path / "other", force=True)
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


def test_inbetween_keeps_the_computed_frames(quick):
    clip = deepmorph.inbetween(quick, 7)  # K = 3: frames at 0, 2, 4, 6
    assert clip.shape == (7, 32, 32, 3) and clip.dtype == np.float32
    np.testing.assert_array_equal(clip[::2], quick.frames)
    with pytest.raises(ValueError, match="frames"):
        quick.inbetween(2)


def test_warp_gives_a_pair_with_its_truth():
    image = disc((16, 16), radius=8.0)
    warped, flow = deepmorph.warp(image, "smooth", 2.0)
    assert warped.shape == (32, 32, 3) and flow.shape == (32, 32, 2)
    assert 1.0 < np.abs(flow).max() <= 2.0 + 1e-5
    with pytest.raises(ValueError, match="field"):
        deepmorph.warp(image, "twist", 2.0)


def test_defaults_are_the_librarys():
    rgb, deep = deepmorph.defaults(), deepmorph.defaults("deep")
    assert rgb["solver"]["steps"] == 15 and rgb["deep"] is None
    assert deep["deep"]["eta"] > 0 and deep["solver"]["params"]["mu"] != rgb["solver"]["params"]["mu"]
    assert deepmorph.defaults(quality="paper")["size"] == {"fit": {"max_side": 512}}
    assert {"flex", "ndarray"} <= set(deepmorph.backends())


@pytest.mark.parametrize(
    "kwargs, error, words",
    [
        (dict(K=0), ValueError, "K = 0"),
        (dict(delta=-1.0), ValueError, "delta = -1"),
        (dict(lambda_=float("nan")), ValueError, "lambda"),
        (dict(colour=3), ValueError, 'unknown parameter "colour"'),
        (dict(eta=2.0), ValueError, "only by model='deep'"),
        (dict(model="deep"), ValueError, "needs VGG19 weights"),
        (dict(model="vgg"), ValueError, "model"),
        (dict(backend="cuda"), ValueError, "backend"),
        (dict(schedule="random"), ValueError, "schedule"),
        (dict(size="big"), ValueError, "size"),
        (dict(points=[[1.0, 2.0, 3.0]]), ValueError, "points"),
        (dict(max_memory=1e-6), MemoryError, "needs about"),
        (dict(model="deep", vgg19="/nonexistent/vgg19.onnx", size=(64, 64)), FileNotFoundError, "nonexistent"),
    ],
)
def test_errors_map_to_python_exceptions(pair, kwargs, error, words):
    settings = dict(QUICK, **kwargs)
    with pytest.raises(error, match=words.replace("(", r"\(").replace(")", r"\)")):
        deepmorph.morph(*pair, **settings)


def test_bad_inputs_are_refused_with_their_reason(pair):
    a, b = pair
    with pytest.raises(FileNotFoundError, match="missing.png"):
        deepmorph.morph("missing.png", b, **QUICK)
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        deepmorph.morph(a[..., :2], b, **QUICK)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        deepmorph.morph(a * 3, b, **QUICK)
    with pytest.raises(ValueError, match="int16"):
        deepmorph.morph(a.astype(np.int16), b, **QUICK)
    with pytest.raises(ValueError):
        deepmorph.morph(np.full_like(a, np.nan), b, **QUICK)


def test_progress_reports_every_sweep_and_its_exception_stops_the_morph(pair):
    events = []
    deepmorph.morph(*pair, progress=events.append, **QUICK)
    joint = [e for e in events if e["phase"] == "joint"]
    assert [(e["level"], e["sweep"]) for e in joint] == [(l, s) for l in range(2) for s in range(7)]
    assert joint[-1]["stop"] == "sweeps" and joint[0]["size"] == (16, 16)

    def fail(event):
        if event["sweep"] == 2:
            raise RuntimeError("stop here")

    with pytest.raises(RuntimeError, match="stop here"):
        deepmorph.morph(*pair, progress=fail, **QUICK)


def test_ctrl_c_stops_after_the_sweep_and_keeps_the_path(tmp_path, pair):
    def interrupt(event):
        if event["level"] == 1 and event["sweep"] == 2:
            os.kill(os.getpid(), signal.SIGINT)
            # The main thread checks for signals every 50 ms; hold the solver until it has.
            time.sleep(0.3)

    # Python raises KeyboardInterrupt only if SIGINT was not ignored when it started; a
    # shell without job control starts background jobs (`.ci/run &`) with SIGINT ignored.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt) as caught:
            deepmorph.morph(*pair, progress=interrupt, **QUICK)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert isinstance(caught.value, deepmorph.Interrupted)
    partial = caught.value.morph
    assert partial.termination != "completed" and "interrupt" in partial.termination
    levels = partial.energy["level"]
    assert levels[-1] == 1 and partial.energy["sweep"][-1] <= 3
    assert partial.frames.shape == (4, 32, 32, 3)
    assert (Path(partial.save(tmp_path / "partial")) / "config.json").is_file()


def busy_rate(keep_going):
    """Iterations per second of a pure-Python loop while `keep_going()`."""
    count, started = 0, time.perf_counter()
    while keep_going():
        for _ in range(1000):
            count += 1
    return count / (time.perf_counter() - started)


def test_the_solve_releases_the_gil(pair):
    start = time.perf_counter()
    baseline = busy_rate(lambda: time.perf_counter() - start < 0.3)
    worker = threading.Thread(
        target=deepmorph.morph, args=pair, kwargs=dict(K=3, levels=2, sweeps=150, size=(64, 64), tol=0.0)
    )
    worker.start()
    time.sleep(0.05)  # past the preparation
    during = busy_rate(worker.is_alive)
    worker.join()
    # Python code runs beside the solve (sharing the cores with the solver's threads); a
    # held GIL would stop it until the morph ends.
    assert during > 0.2 * baseline, (during, baseline)


def test_landmarks_from_an_array_steer_the_morph(pair):
    points = np.array([[13.0, 14.0, 19.0, 17.0]])  # x_a, y_a, x_b, y_b: the discs' centres
    m = deepmorph.morph(*pair, points=points, **QUICK)
    assert m.config["landmarks"][0]["a"] == [13.0, 14.0]
    assert m.metrics["landmarks"]["max"] < 1.0


def test_deep_morph_with_the_stand_in_weights(tmp_path, pair):
    weights = SHARED_DATA / "vgg19" / "vgg19_hed_stand_in.onnx"
    if not weights.is_file():
        if os.environ.get("DEEPMORPH_REQUIRE_SHARED_DATA") == "1":
            pytest.fail(f"{weights} not found, and DEEPMORPH_REQUIRE_SHARED_DATA=1")
        pytest.skip(f"{weights} not found (the team's shared data)")
    # The deep model's sizes are multiples of 16, at least 64.
    m = deepmorph.morph(*pair, model="deep", vgg19=weights, K=2, levels=2, sweeps=2, pre_sweeps=1, size=(64, 64))
    assert m.frames.shape == (3, 64, 64, 3)
    assert m.config["config"]["deep"]["pre_sweeps"] == 1
    assert len(m.config["outcome"]["tap_rms"]) == 5
    assert "feature_path" in m.metrics
    phases = set()
    deepmorph.morph(*pair, model="deep", vgg19=str(weights), K=2, levels=2, sweeps=1, pre_sweeps=1,
                    size=(64, 64), progress=lambda e: phases.add(e["phase"]))
    assert phases == {"features", "joint"}


def test_progress_true_reports_each_level_on_stderr(capsys, pair):
    deepmorph.morph(*pair, progress=True, **QUICK)
    # tqdm's bar where it is installed, else one line per level: either names the levels.
    assert "level 2/2" in capsys.readouterr().err


def test_threads_share_a_morph_without_deadlock(tmp_path, pair):
    m = deepmorph.morph(*pair, **QUICK)
    done = []

    def work(i):
        folder = m.save(tmp_path / f"out{i}")
        done.append((Path(folder).name, m.metrics["size"], m.termination, repr(m), m.inbetween(5).shape))

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert not any(t.is_alive() for t in threads), "a thread hangs on the morph"
    assert sorted(d[0] for d in done) == [f"out{i}" for i in range(4)]
    assert all(d[1:3] == ([32, 32], "completed") and d[4] == (5, 32, 32, 3) for d in done)
