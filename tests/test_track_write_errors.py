"""``quatrack track`` outputs that cannot be written name the output, the system's reason and what
is left (user report: ``--out /dev/full`` said "error: [Errno 28] No space left on device", a full
disk the same, ``--out /proc/version`` "[Errno 5] Input/output error", ``--overlay /proc/x.mp4``
"cannot write ... here"; an overlay cut off by a full disk was put in place in silence)."""

from __future__ import annotations

import errno
import os

import pytest

from quatrack import track_cli
from quatrack.recognition import trackio
from quatrack.testing.scenes import EXAMPLE

from test_track_cli import _track

VIDEO = ["--video", str(EXAMPLE / "box.mp4")]


def _full_after(rows: int, mode: str):
    """``open`` for track_cli whose files in ``mode`` fail with ENOSPC once ``rows`` lines are written."""
    real = open

    def fake(path, m="r", *args, **kwargs):
        f = real(path, m, *args, **kwargs)
        if m != mode:
            return f
        written = [0]
        write = f.write

        def failing(data):
            written[0] += 1
            if written[0] > rows:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return write(data)

        f.write = failing
        return f

    return fake


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err and "Errno" not in err, err
    return err


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full")
def test_out_on_dev_full_names_the_output_and_the_reason(tmp_path, capsys):
    assert _track(tmp_path, *VIDEO, "--max-frames", "2", "--out", "/dev/full") == 2
    assert _one_line(capsys) == ("quatrack track: error: --out /dev/full: cannot write (No space left on device) at "
                                 "the end of the run (2 frames tracked); the poses are not all written; free some "
                                 "space or write the poses elsewhere")


def test_a_full_disk_stops_the_run_at_the_frame_and_keeps_the_old_file(tmp_path, capsys, monkeypatch):
    out, overlay = tmp_path / "poses.csv", tmp_path / "overlay.mp4"
    out.write_text("the old poses\n")
    monkeypatch.setattr(track_cli, "open", _full_after(3, "w"), raising=False)  # header, rows 0 and 1
    assert _track(tmp_path, *VIDEO, "--max-frames", "5", "--out", str(out), "--overlay", str(overlay)) == 2
    assert _one_line(capsys) == (f"quatrack track: error: --out {out}: cannot write (No space left on device) at "
                                 f"frame 2; the run stopped there; {out} is as it was before the run (the partial "
                                 f"file was removed; --overlay not written either); free some space or write the "
                                 f"poses elsewhere")
    assert out.read_text() == "the old poses\n" and sorted(p.name for p in tmp_path.iterdir()) == ["poses.csv"]
    new = tmp_path / "new.csv"
    assert _track(tmp_path, *VIDEO, "--max-frames", "5", "--out", str(new)) == 2
    assert f"; no {new} was made (the partial file was removed)" in _one_line(capsys)
    assert not new.exists()


def test_a_plot_on_a_full_disk_names_it(tmp_path, capsys, monkeypatch):
    out, plot = tmp_path / "poses.csv", tmp_path / "plot.png"
    monkeypatch.setattr(track_cli, "open", _full_after(0, "wb"), raising=False)
    assert _track(tmp_path, *VIDEO, "--max-frames", "2", "--out", str(out), "--plot", str(plot)) == 2
    assert _one_line(capsys) == (f"quatrack track: error: --plot {plot}: cannot write (No space left on device); no "
                                 f"output of the run was written (files of the same names are as they were)")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="no /proc")
def test_an_overlay_that_cannot_be_opened_names_its_file(tmp_path, capsys):
    out = tmp_path / "poses.csv"
    assert _track(tmp_path, *VIDEO, "--max-frames", "2", "--out", str(out), "--overlay", "/proc/x.mp4") == 2
    assert _one_line(capsys).startswith("quatrack track: error: --overlay /proc/x.mp4: cannot write a 640×480 MP4 "
                                        "video there")
    assert not out.exists()


def test_an_overlay_cut_short_is_not_put_in_place(tmp_path, capsys, monkeypatch):
    """OpenCV's writer on a full disk stops in silence: the video, without its index, was renamed
    into place and the run ended with exit 0. It is read back: cut short, it is an error."""
    close = trackio.VideoOut.close

    def cut_short(self):
        close(self)
        with open(self.path, "r+b") as f:
            f.truncate(4096)

    monkeypatch.setattr(trackio.VideoOut, "close", cut_short)
    out, overlay = tmp_path / "poses.csv", tmp_path / "overlay.mp4"
    assert _track(tmp_path, *VIDEO, "--max-frames", "2", "--out", str(out), "--overlay", str(overlay)) == 2
    assert _one_line(capsys) == (f"quatrack track: error: --overlay {overlay}: the video could not be written whole "
                                 f"(the written file cannot be read back)")
    assert list(tmp_path.iterdir()) == []
