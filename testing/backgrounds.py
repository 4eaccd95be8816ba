"""Room backgrounds for rendered scenes, frozen as files.

The backgrounds of the zoo (:mod:`.zoo`) and of the cookie-box scenes (:mod:`.scenes`) are frames
of the bundled ``box.mp4`` with the real box painted out. Painting it out needs the box's pose,
found by ``locate``; computed on the fly, every change to recognition would move the paint and so
redraw every benchmark scene and zoo model, and no before/after comparison would be like for like.
So they are computed once and stored in ``testing/data/backgrounds/`` (20 JPEGs, 640×480, quality
85, ~0.56 MB; package data, licence in that folder's README): :func:`frozen_backgrounds` loads them.

Regenerate them (only on purpose: it changes every benchmark scene) with::

    python -m quatrack.testing.backgrounds [--out DIR]

which runs :func:`quatrack.testing.scenes.inpaint_video_backgrounds` with the recognition of the
day and writes ``bg00.jpg`` … ``bg19.jpg``.
"""

from __future__ import annotations

import argparse
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

DATA = Path(__file__).resolve().parent / "data" / "backgrounds"
COUNT = 20
QUALITY = 85


def background_paths(directory: str | Path = DATA) -> list[Path]:
    return sorted(Path(directory).glob("bg*.jpg"))


@lru_cache(maxsize=1)
def frozen_backgrounds() -> tuple[np.ndarray, ...]:
    """The stored backgrounds (BGR uint8, read-only arrays), loaded once per process."""
    paths = background_paths()
    if len(paths) != COUNT:
        raise FileNotFoundError(f"{DATA}: {len(paths)} of {COUNT} backgrounds (bg00.jpg … bg19.jpg); "
                                "regenerate with `python -m quatrack.testing.backgrounds`")
    out = []
    for p in paths:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise OSError(f"{p}: not a readable image")
        img.setflags(write=False)  # shared by every caller in the process
        out.append(img)
    return tuple(out)


def regenerate(directory: str | Path = DATA, quality: int = QUALITY) -> list[Path]:
    """Recompute the backgrounds from ``box.mp4`` and write them to ``directory`` (old ``bg*.jpg``
    there are replaced). Returns the paths written."""
    from .scenes import inpaint_video_backgrounds

    bgs = inpaint_video_backgrounds(limit=COUNT)
    if len(bgs) != COUNT:
        raise RuntimeError(f"only {len(bgs)} of {COUNT} frames of box.mp4 gave a verified pose of the box")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for p in background_paths(directory):
        p.unlink()
    paths = []
    for i, bg in enumerate(bgs):
        p = directory / f"bg{i:02d}.jpg"
        if not cv2.imwrite(str(p), bg, [cv2.IMWRITE_JPEG_QUALITY, int(quality)]):
            raise OSError(f"{p}: could not write")
        paths.append(p)
    frozen_backgrounds.cache_clear()
    return paths


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m quatrack.testing.backgrounds",
                                 description="Recompute the rendered scenes' room backgrounds from box.mp4 "
                                             "(the box painted out at its located pose) and store them as JPEGs.")
    ap.add_argument("--out", default=str(DATA), help=f"directory to write bg00.jpg … (default {DATA})")
    ap.add_argument("--quality", type=int, default=QUALITY, help=f"JPEG quality (default {QUALITY})")
    args = ap.parse_args(argv)
    paths = regenerate(args.out, args.quality)
    total = sum(p.stat().st_size for p in paths)
    print(f"wrote {len(paths)} backgrounds to {args.out} ({total / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
