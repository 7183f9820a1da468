"""CLI messages of issue 25 (items 7 and 9): Ctrl-C, the settings-mismatch error, valid counts over the region,
a closed pipe, option help, reprs and the messages of wrong inputs."""
import numpy as np
import pytest
from click.testing import CliRunner
from test_cli_track import FakeTracker, fake, images  # noqa: F401 - the fixtures

from dic.cli import main
from dic.store import read_results


class InterruptedTracker(FakeTracker):
    """Ctrl-C (KeyboardInterrupt) while frame 2 is tracked: frame 1 is finished and written."""

    def track(self, current, guess=None):
        if FakeTracker.calls == 1:
            raise KeyboardInterrupt
        return super().track(current, guess)


def test_ctrl_c_in_track_says_what_is_saved_and_how_to_resume(images, tmp_path, monkeypatch):  # noqa: F811
    import dic.commands.track as cmd

    FakeTracker.calls = 0
    monkeypatch.setattr(cmd, "_make_tracker", lambda ref, **kw: InterruptedTracker(ref, **kw))
    out = tmp_path / "res.h5"
    r = CliRunner().invoke(main, ["track", *images, "-o", str(out), "--step", "8"], catch_exceptions=False)
    assert r.exit_code == 130, r.output
    assert f"1 frame saved in {out}; run the same command again to resume" in r.output
    assert "Aborted!" not in r.output
    assert read_results(out).indices == [1]
    # the same command resumes: frame 1 is skipped, frame 2 computed
    FakeTracker.calls = 0
    monkeypatch.setattr(cmd, "_make_tracker", lambda ref, **kw: FakeTracker(ref, **kw))
    r = CliRunner().invoke(main, ["track", *images, "-o", str(out), "--step", "8"], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    assert "1 frame(s) were already in" in r.output and read_results(out).indices == [1, 2]


def test_ctrl_c_before_any_frame_says_none_was_saved(images, tmp_path, monkeypatch):  # noqa: F811
    import dic.commands.track as cmd

    def stop(ref, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(cmd, "_make_tracker", stop)
    out = tmp_path / "res.h5"
    r = CliRunner().invoke(main, ["track", *images, "-o", str(out), "--step", "8"], catch_exceptions=False)
    assert r.exit_code == 130 and f"no frame was saved in {out} yet" in r.output, r.output


def test_every_refusal_to_resume_names_overwrite(images, tmp_path, fake):  # noqa: F811 - fixtures
    """Another reference image, other settings, another kind of file: each refusal names --overwrite."""
    out = tmp_path / "res.h5"
    assert CliRunner().invoke(main, ["track", *images, "-o", str(out), "--step", "8"]).exit_code == 0
    for args in ([images[1], images[0], images[2]], [*images, "--step", "6"]):
        args = [*args, "--step", "8"] if "--step" not in args else args
        r = CliRunner().invoke(main, ["track", *args, "-o", str(out)])
        assert r.exit_code == 1 and "--overwrite" in r.output, r.output
        assert "Traceback" not in r.output
    import h5py

    from dic.store import ResultWriter

    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as h5:
        h5.attrs["format"] = "someone else's"
    with pytest.raises(ValueError, match="--overwrite"):  # not a Specula file
        ResultWriter(other, settings={}, mode="resume").close()
