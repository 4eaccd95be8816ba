"""SIGTERM while ``quatrack track`` sets up (the model loading, a stream opening) is an interrupt,
as Ctrl-C is there: "interrupted", exit 130 (it killed the process silently, exit -15)."""

from __future__ import annotations

import os
import signal

from quatrack.cli import main
from quatrack.recognition import trackio
from quatrack.testing.scenes import EXAMPLE, example_store


def test_sigterm_while_the_source_opens_is_an_interrupt(monkeypatch, tmp_path, capsys):
    taken = []  # (the handler before the run: without the fix it took the signal, and the run went on)
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: taken.append(signum))
    try:
        def opening(*args, **kwargs):  # (a stream still opening when `docker stop` comes)
            os.kill(os.getpid(), signal.SIGTERM)
            raise AssertionError("SIGTERM was not taken for an interrupt")

        monkeypatch.setattr(trackio, "open_frames", opening)
        out = tmp_path / "poses.csv"
        rc = main(["track", "--object", "cookie-box", "--camera", str(EXAMPLE / "camera.json"), "--video", "0",
                   "--store", str(example_store()), "--out", str(out)])
        err = capsys.readouterr().err
        assert rc == 130 and "interrupted" in err and not taken, err
        assert not out.exists() and os.listdir(tmp_path) == []
        os.kill(os.getpid(), signal.SIGTERM)  # (the handler before the run is back)
        assert taken == [signal.SIGTERM]
    finally:
        signal.signal(signal.SIGTERM, previous)
