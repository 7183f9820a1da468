"""Sequences on Dask (dic.sequence.distributed): ``track_sequence(client=)`` and ``specula track --workers/--scheduler``
on a LocalCluster of 2 worker processes: results identical to one process (guess="none"), resume, a worker
killed mid-run, an unreachable scheduler. About 30-60 s in all (one cluster for the module)."""
import threading
import time

import numpy as np
import pytest
from click.testing import CliRunner

distributed = pytest.importorskip("distributed")

from dic.sequence import track_sequence  # noqa: E402
from dic.store import read_results  # noqa: E402
from dic.synth import speckle_pair  # noqa: E402
from kernels.conventions import Status  # noqa: E402

pytestmark = pytest.mark.dask

SHAPE = (96, 112)
N_FRAMES = 8


def truth(k):
    return lambda x, y: (0.25 * k + 0.002 * k * (x - 56), -0.2 * k + 0.001 * k * (y - 48))


@pytest.fixture(scope="module")
def sequence():
    ref, _ = speckle_pair(SHAPE, (0, 0), seed=5)
    return ref, [speckle_pair(SHAPE, truth(k), seed=5)[1] for k in range(1, N_FRAMES + 1)]


@pytest.fixture(scope="module")
def client():
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None) as cluster, \
            distributed.Client(cluster) as c:
        import dic

        # the worker processes import this checkout's packages
        assert set(c.run(lambda: __import__("dic").__file__).values()) == {dic.__file__}
        yield c


def _same(a, b, frames=None):
    ra, rb = read_results(a), read_results(b)
    assert sorted(ra.frames) == sorted(rb.frames) == (frames or list(range(1, N_FRAMES + 1)))
    for k in ra.frames:
        fa, fb = ra.frames[k], rb.frames[k]
        for name in ("points", "u", "v", "params", "zncc", "status", "valid", "sigma_u", "sigma_v"):
            assert np.array_equal(getattr(fa, name), getattr(fb, name), equal_nan=True), (k, name)
        for name in fa.strain or {}:
            assert np.array_equal(fa.strain[name], fb.strain[name], equal_nan=True), (k, name)
        assert fa.attrs["reference_index"] == fb.attrs["reference_index"]
    assert ra.settings == rb.settings


@pytest.mark.parametrize("strategy", ["fixed", "every:3"])
def test_identical_to_one_process(sequence, client, tmp_path, strategy):
    ref, frames = sequence
    seen = []
    s = track_sequence(ref, frames, tmp_path / "d.h5", reference=strategy, step=8, device="cpu", client=client,
                       callback=lambda k, f, e: seen.append(k))
    # every:3 checks composed frames by default, on Dask as on one process
    one = track_sequence(ref, frames, tmp_path / "one.h5", reference=strategy, step=8, device="cpu", guess="none")
    _same(tmp_path / "d.h5", tmp_path / "one.h5")
    assert s.n_mismatch.tolist() == one.n_mismatch.tolist() == [0] * N_FRAMES
    if strategy != "fixed":  # a clean run: the check changes nothing (bit for bit the run without it)
        assert read_results(tmp_path / "d.h5").settings["verify_composed"] is True
        off = tmp_path / "off.h5"
        track_sequence(ref, frames, off, reference=strategy, step=8, device="cpu", client=client, verify_composed=False)
        ra, rb = read_results(tmp_path / "d.h5"), read_results(off)
        for k in ra.frames:
            for name in ("u", "v", "params", "zncc", "status", "valid", "sigma_u", "sigma_v"):
                assert np.array_equal(getattr(ra.frames[k], name), getattr(rb.frames[k], name), equal_nan=True)
            assert ra.frames[k].attrs.get("composed_mismatch", 0) == 0 and "composed_mismatch" not in rb.frames[k].attrs
    assert seen == list(range(1, N_FRAMES + 1))  # written in frame order
    assert [f["index"] for f in s.frames] == list(range(1, N_FRAMES + 1))
    assert [f["reference_index"] for f in s.frames] == [f["reference_index"] for f in one.frames]
    from dic.sequence import distributed as dd

    assert set(client.run(lambda: len(dd._CACHE)).values()) == {0}  # the workers let the run's references go
    res = read_results(tmp_path / "d.h5")
    assert res.settings["guess"] == "none"
    for k in (1, N_FRAMES):  # and the exact field is followed
        f = res.frames[k]
        tu, tv = truth(k)(f.points[:, 0], f.points[:, 1])
        assert f.valid.mean() >= 0.85 and np.sqrt(np.mean((f.u[f.valid] - tu[f.valid]) ** 2)) < 0.05


def test_scheduler_address_connected_and_closed(sequence, client, tmp_path):
    """client= as an address: connected for the run and closed after it (no client left on the scheduler)."""
    ref, frames = sequence

    def n_clients():
        return client.run_on_scheduler(lambda dask_scheduler: len(dask_scheduler.clients))

    before = n_clients()
    track_sequence(ref, frames[:3], tmp_path / "a.h5", step=8, device="cpu", client=client.scheduler.address)
    track_sequence(ref, frames[:3], tmp_path / "one.h5", step=8, device="cpu", guess="none")
    _same(tmp_path / "a.h5", tmp_path / "one.h5", frames=[1, 2, 3])
    deadline = time.time() + 10
    while n_clients() > before and time.time() < deadline:
        time.sleep(0.1)
    assert n_clients() == before


def test_resume_on_dask(sequence, client, tmp_path):
    ref, frames = sequence
    out = tmp_path / "r.h5"
    track_sequence(ref, frames[:3], out, reference="every:2", step=8, device="cpu", guess="none")  # one process
    s = track_sequence(ref, frames, out, reference="every:2", step=8, device="cpu", client=client)
    assert s.skipped == 3 and [f["index"] for f in s.frames] == list(range(4, N_FRAMES + 1))
    track_sequence(ref, frames, tmp_path / "one.h5", reference="every:2", step=8, device="cpu", guess="none")
    _same(out, tmp_path / "one.h5")
    other = [frames[0], frames[0] + 1.0] + frames[2:]  # a finished frame's image changed: refused, as on one machine
    with pytest.raises(ValueError, match="frame 2"):
        track_sequence(ref, other, out, reference="every:2", step=8, device="cpu", client=client)


def test_wrong_match_carried_by_a_reference_update_flagged_as_on_one_process(sequence, client, tmp_path):
    """every:2: frame 2 (against the reference image, the key frame of the next block) reports a 4 x 4 block of
    points 1 px off in u. On Dask the check of composed results flags the points of frames 3 and 4 that inherit
    the wrong match (more than 0.75 px off the exact field), none within 0.05 px, and the file and summary are
    those of one process with guess="none" (the check runs in the client before frame 4's result anchors the
    next block). Without the check the error is carried (shown first)."""
    ref, frames = sequence
    wrong = frames[1]

    def make_tracker(image, points):  # picklable (a closure): corrupts frame 2 against the reference image
        import numpy as np

        from dic._track import Tracker

        tracker = Tracker(image, step=8, device="cpu") if points is None else Tracker(image, points=points,
                                                                                     device="cpu")
        track = tracker.track

        def corrupted(current, **kw):
            field = track(current, **kw)
            if points is None and np.array_equal(np.asarray(current), wrong):
                xs, ys = np.unique(field.points[:, 0]), np.unique(field.points[:, 1])
                j = np.flatnonzero(np.isin(field.points[:, 0], xs[len(xs) // 2 - 2:len(xs) // 2 + 2])
                                   & np.isin(field.points[:, 1], ys[len(ys) // 2 - 2:len(ys) // 2 + 2]))
                field.u[j] += 1.0
                field.params[j, 0] += 1.0
            return field

        tracker.track = corrupted
        return tracker

    kw = dict(reference="every:2", make_tracker=make_tracker, points=None, order=1, strain_window=0)

    def errors(f, k):
        tu, tv = truth(k)(f.points[:, 0], f.points[:, 1])
        return np.hypot(f.u - tu, f.v - tv)

    track_sequence(ref, frames, tmp_path / "plain.h5", client=client, verify_composed=False, **kw)
    plain = read_results(tmp_path / "plain.h5")
    for k in (3, 4):  # the problem, shown: inherited by the frames against the moved reference, valid
        assert np.count_nonzero(plain.frames[k].valid & (errors(plain.frames[k], k) > 0.75)) >= 8
    d = track_sequence(ref, frames, tmp_path / "d.h5", client=client, **kw)
    one = track_sequence(ref, frames, tmp_path / "one.h5", guess="none", **kw)
    _same(tmp_path / "d.h5", tmp_path / "one.h5")
    assert d.n_mismatch.tolist() == one.n_mismatch.tolist()
    res = read_results(tmp_path / "d.h5")
    by_frame = dict(zip(d.indices.tolist(), d.n_mismatch.tolist()))
    for k in (3, 4):
        f = res.frames[k]
        flagged = f.status == int(Status.COMPOSED_MISMATCH)
        err = errors(f, k)
        assert np.all(flagged[(f.valid | flagged) & (err > 0.75)]) and not np.any(flagged & (err < 0.05))
        assert f.attrs["composed_mismatch"] == np.count_nonzero(flagged) == by_frame[k] >= 8
    assert by_frame[1] == by_frame[2] == 0


def test_worker_killed_mid_run(sequence, client, tmp_path):
    """The first frame tracked kills its worker process: the frame is retried on another worker, nothing is
    lost or written twice, results as on one process."""
    ref, frames = sequence
    marker = tmp_path / "killed"

    def make_tracker(image, points, marker=str(marker)):
        import os

        from dic._track import Tracker

        class KillsItsWorkerOnce:
            def __init__(self, tracker):
                self.tracker, self.points, self.order = tracker, tracker.points, tracker.order

            def track(self, image, guess=None):
                if not os.path.exists(marker):
                    open(marker, "w").close()
                    os._exit(1)
                return self.tracker.track(image, guess=guess)

        kw = {"step": 8} if points is None else {"points": points}
        return KillsItsWorkerOnce(Tracker(image, device="cpu", **kw))

    seen = []
    s = track_sequence(ref, frames, tmp_path / "k.h5", client=client, make_tracker=make_tracker, settings={"step": 8},
                       callback=lambda k, f, e: seen.append(k))
    assert marker.exists()  # a worker died
    assert seen == list(range(1, N_FRAMES + 1)) and [f["index"] for f in s.frames] == seen
    track_sequence(ref, frames, tmp_path / "one.h5", step=8, device="cpu", guess="none", settings={"step": 8})
    _same(tmp_path / "k.h5", tmp_path / "one.h5")
    deadline = time.time() + 30  # the nanny restarts the worker
    while len(client.scheduler_info()["workers"]) < 2 and time.time() < deadline:
        time.sleep(0.2)


def test_frame_that_keeps_killing_its_workers(sequence, client, tmp_path):
    """A frame whose every try kills its worker: a clear message after distributed's retries, and every frame
    before it in the file (written once)."""
    ref, frames = sequence
    out = tmp_path / "k.h5"

    def make_tracker(image, points, bad=frames[3]):
        import os

        import numpy as np

        from dic._track import Tracker

        class KillsOnFrame4:
            def __init__(self, tracker):
                self.tracker, self.points, self.order = tracker, tracker.points, tracker.order

            def track(self, image, guess=None):
                if np.array_equal(image, bad):
                    os._exit(1)
                return self.tracker.track(image, guess=guess)

        kw = {"step": 8} if points is None else {"points": points}
        return KillsOnFrame4(Tracker(image, device="cpu", **kw))

    with pytest.raises(ValueError, match=r"^frame \d+ \(array\): the Dask cluster could not compute it \(KilledWorker: "
                                         r".*frames before it are saved in .*k\.h5$") as failure:
        track_sequence(ref, frames, out, client=client, make_tracker=make_tracker, settings={"step": 8})
    # the frame reported is frame 4, or an earlier one that was running on the workers frame 4 killed (a task
    # running on a worker that dies counts as one of its tries too, so under load it can run out of tries
    # first); either way every frame before the reported one is in the file, once
    reported = int(str(failure.value).split()[1])
    assert 1 <= reported <= 4
    assert sorted(read_results(out).frames) == list(range(1, reported))
    deadline = time.time() + 30  # the nanny restarts the worker
    while len(client.scheduler_info()["workers"]) < 2 and time.time() < deadline:
        time.sleep(0.2)


def test_refused_settings(sequence, client, tmp_path):
    ref, frames = sequence
    for kw, match in ((dict(reference="incremental"), "'incremental' cannot be distributed"),
                      (dict(reference="auto"), "'auto' cannot be distributed"),
                      (dict(guess="previous"), "guess='previous' chains"),
                      (dict(client=12), "client must be a distributed.Client or a scheduler address")):
        with pytest.raises(ValueError, match=match):
            track_sequence(ref, frames, tmp_path / "x.h5", step=8, device="cpu", **{"client": client, **kw})
    lock = threading.Lock()

    def make_tracker(image, points, lock=lock):  # holds a lock: cannot go to the workers
        from dic._track import Tracker

        return Tracker(image, device="cpu", **({"step": 8} if points is None else {"points": points}))

    with pytest.raises(ValueError, match=r"make_tracker cannot be sent to the Dask workers \(TypeError: cannot pickle "
                                         r"'_thread.lock' object\); with client= it must be picklable"):
        track_sequence(ref, frames, tmp_path / "x.h5", client=client, make_tracker=make_tracker, settings={})
    with pytest.raises(ValueError, match="guess must be 'previous' or 'none'"):
        track_sequence(ref, frames, tmp_path / "x.h5", step=8, device="cpu", guess="chain")
    assert not (tmp_path / "x.h5").exists()


def test_address_that_is_not_a_scheduler(sequence, tmp_path):
    """A server that answers something else (here an HTTP error page) at the address: the same clear message."""
    import socket
    import threading

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen()
    port = server.getsockname()[1]

    def answer():
        for _ in range(5):
            try:
                conn, _ = server.accept()
            except OSError:
                return
            conn.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n" * 8)
            conn.close()

    threading.Thread(target=answer, daemon=True).start()
    ref, frames = sequence
    try:
        with pytest.raises(ValueError, match=rf"^cannot reach the Dask scheduler at tcp://127.0.0.1:{port} within 5 s "):
            track_sequence(ref, frames, tmp_path / "x.h5", step=8, device="cpu", client=f"tcp://127.0.0.1:{port}")
    finally:
        server.close()
    assert not (tmp_path / "x.h5").exists()


def _images(tmp_path, sequence):
    from dic.io import write_image

    ref, frames = sequence
    paths = []
    for k, img in enumerate([ref, *frames]):
        paths.append(str(tmp_path / f"img_{k:02d}.tif"))
        write_image(paths[-1], np.clip(np.round(img), 0, 255).astype(np.uint8))
    return paths


def test_cli_workers_and_unreachable_scheduler(sequence, tmp_path):
    from dic.cli import main

    paths = _images(tmp_path, sequence)
    runner = CliRunner()
    out = tmp_path / "cli.h5"
    r = runner.invoke(main, ["track", *paths, "-o", str(out), "--step", "8", "--device", "cpu", "--workers", "2",
                             "--reference", "every:4", "-q"])
    assert r.exit_code == 0, r.output
    track_sequence(paths[0], paths[1:], tmp_path / "one.h5", reference="every:4", guess="none", step=8, device="cpu",
                   subset=21, order=1)
    ra, rb = read_results(out), read_results(tmp_path / "one.h5")
    for k in range(1, N_FRAMES + 1):
        for name in ("u", "v", "params", "status", "valid"):
            assert np.array_equal(getattr(ra.frames[k], name), getattr(rb.frames[k], name), equal_nan=True)

    t0 = time.perf_counter()
    r = runner.invoke(main, ["track", *paths, "-o", str(tmp_path / "s.h5"), "--device", "cpu",
                             "--scheduler", "tcp://127.0.0.1:1", "-q"])
    assert r.exit_code == 1 and isinstance(r.exception, SystemExit), r.output  # a message, no traceback
    assert "Error: cannot reach the Dask scheduler at tcp://127.0.0.1:1 within 5 s" in r.output
    assert time.perf_counter() - t0 < 20
    assert not (tmp_path / "s.h5").exists()

    for args, match in ((["--workers", "2", "--reference", "incremental"], "cannot be distributed"),
                        (["--workers", "2", "--scheduler", "tcp://127.0.0.1:1"], "not both"),
                        (["--workers", "0"], "--workers")):
        r = runner.invoke(main, ["track", *paths, "-o", str(tmp_path / "s.h5"), *args])
        assert r.exit_code == 2 and match in r.output, r.output


@pytest.fixture(scope="module")
def stereo_lab():
    """A 320 x 240 px stereo rig looking at a speckled plane, in 4 states (rigid translations)."""
    from dataclasses import replace

    from dic.lab import Displacement, LabCamera, Scene, SpecklePlane, render, stereo_rig
    from dic.synth import make_speckle

    cams = [LabCamera.from_lens(name=name, size=(320, 240), focal_length_mm=12.0, f_number=float("inf"),
                                focus_distance_mm=1000.0, position=(x, 0.0, 0.0), look_at_point=(0.0, 0.0, 1000.0),
                                exposure_dn=200.0, bit_depth=8)
            for name, x in (("left", -150.0), ("right", 150.0))]
    speckle = make_speckle(region=(-5, -5, 305, 255), radius=1.2, density=0.5, bits=None, seed=3)
    plane = SpecklePlane.facing(center=(0.0, 0.0, 1000.0), normal=(0.0, 0.0, -1.0), size=(300.0, 250.0), speckle=speckle)
    states = []
    for k in range(4):
        t_local = plane.R_world_surface.T @ (np.array([0.4, -0.2, 0.8]) * k)
        p = replace(plane, displacement=Displacement(np.broadcast_to(t_local, (2, 2, 3)).copy(), (0.0, 0.0),
                                                     (300.0, 250.0)))
        states.append(tuple(render(Scene(cameras=cams, planes=[p]), i, samples=4, seed=10 * k + i) for i in range(2)))
    left, right = cams
    return stereo_rig(left, right), states


def test_stereo_identical_to_one_process(stereo_lab, client, tmp_path):
    from dic.sequence import read_stereo, stereo_sequence

    rig, pairs = stereo_lab
    seen = []
    d = stereo_sequence(rig, pairs, tmp_path / "d.h5", step=20, device="cpu", client=client,
                        callback=lambda k, f, strain: seen.append(k))
    one = stereo_sequence(rig, pairs, tmp_path / "one.h5", step=20, device="cpu", guess="none")
    assert seen == [0, 1, 2, 3] and list(d.indices) == list(one.indices) == [0, 1, 2, 3]
    a, b = read_stereo(tmp_path / "d.h5"), read_stereo(tmp_path / "one.h5")
    assert a.settings == b.settings and a.settings["guess"] == "none"
    from dic.field3d import SCALAR_FIELDS

    assert sorted(a.fields) == sorted(b.fields) == [0, 1, 2, 3]
    for k in a.fields:
        fa, fb = a.fields[k], b.fields[k]
        for name in ("points", "status", "strain_valid", *SCALAR_FIELDS):
            assert np.array_equal(getattr(fa, name), getattr(fb, name), equal_nan=True), (k, name)
    last = a.fields[3]
    assert np.count_nonzero(np.isfinite(last.U)) > 0.5 * last.U.size
    # resume on the cluster: the finished states are skipped
    stereo_sequence(rig, pairs[:2], tmp_path / "r.h5", step=20, device="cpu", guess="none")
    r = stereo_sequence(rig, pairs, tmp_path / "r.h5", step=20, device="cpu", client=client)
    assert list(r.indices) == [2, 3] and r.skipped == 2
    with pytest.raises(ValueError, match="guess='previous' chains each state"):
        stereo_sequence(rig, pairs, tmp_path / "x.h5", step=20, device="cpu", client=client, guess="previous")


def test_stereo_cli_on_a_scheduler(stereo_lab, client, tmp_path):
    from dic.cli import main
    from dic.io import write_image
    from dic.sequence import read_stereo

    rig, pairs = stereo_lab
    paths = []
    for k, (a, b) in enumerate(pairs):
        for side, img in (("L", a), ("R", b)):
            paths.append(str(tmp_path / f"{side}{k}.png"))
            write_image(paths[-1], img)
    rig.save(tmp_path / "rig.json")
    runner = CliRunner()
    base = ["stereo", "--rig", str(tmp_path / "rig.json"), *paths, "--step", "20", "--device", "cpu", "-q"]
    r = runner.invoke(main, [*base, "-o", str(tmp_path / "s.h5"), "--scheduler", client.scheduler.address])
    assert r.exit_code == 0, r.output
    res = read_stereo(tmp_path / "s.h5")
    assert res.indices == [0, 1, 2, 3] and res.settings["guess"] == "none"
    r = runner.invoke(main, [*base, "-o", str(tmp_path / "x.h5"), "--scheduler", "tcp://127.0.0.1:1"])
    assert r.exit_code == 1 and "Error: cannot reach the Dask scheduler at tcp://127.0.0.1:1 within 5 s" in r.output
    r = runner.invoke(main, [*base, "-o", str(tmp_path / "x.h5"), "--scheduler", "tcp://127.0.0.1:1", "--workers", "2"])
    assert r.exit_code == 2 and "not both" in r.output
    assert not (tmp_path / "x.h5").exists()
