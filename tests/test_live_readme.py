"""README's "Live sources" part: each sentence once (two versions of the same sentences were
left side by side), and every option of ``track`` for a live source named."""

from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parent.parent / "README.md"


def _live_sources() -> str:
    text = README.read_text(encoding="utf-8")
    start = text.index("**Live sources.**")
    return " ".join(text[start:text.index("```", start)].split())


def test_the_live_sources_part_says_each_sentence_once():
    sentences = [s.strip() for s in re.split(r"(?<=[.;:])\s+", _live_sources()) if len(s.strip()) > 30]
    repeated = {s for s in sentences if sentences.count(s) > 1}
    assert not repeated, repeated
    # (the repeated fragment of the old text, with two versions of the rate rule)
    assert _live_sources().count("at the pace the frames") == 1


def test_the_track_heading_and_options_name_every_option_of_track():
    # (the list left out --stall-timeout)
    import argparse

    from quatrack.track_cli import add_arguments

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    text = README.read_text(encoding="utf-8")
    start = text.index("### Track in video: `quatrack track")
    listed = text[start:text.index("`.", text.index("Options:", start))]
    options = {o for a in parser._actions for o in a.option_strings if o.startswith("--") and o != "--help"}
    assert {o for o in options if o not in listed} == set()


def test_the_live_sources_part_names_every_live_option():
    part = _live_sources()
    for option in ("--stall-timeout", "--max-frames", "--fps", "--relocate-every"):
        assert f"`{option}" in part, option
