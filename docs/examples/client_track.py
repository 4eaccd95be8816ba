"""Track the bundled video through a running quatrack server with the Python client.

    quatrack serve &                      # in another terminal (the cookie box trained)
    python docs/examples/client_track.py --url http://127.0.0.1:8000 --frames 30

Prints one line per frame (status and position) and the pose of the video's first frame found
by the one-image endpoint. Run by tests/test_client.py against a real server.
"""

from __future__ import annotations

import argparse
import sys

from quatrack.client import Client, QuatrackError
from quatrack.examples import example_dir
from quatrack.recognition.trackio import open_frames


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", default="http://127.0.0.1:8000")
    ap.add_argument("--token", default=None, help="default: $QUATRACK_API_TOKEN")
    ap.add_argument("--object", default="cookie-box")
    ap.add_argument("--frames", type=int, default=30)
    args = ap.parse_args()
    example = example_dir("cookie-box")
    camera = example / "camera.json"
    try:
        with Client(args.url, object=args.object, token=args.token) as client:
            with open_frames(video=str(example / "box.mp4"), max_frames=args.frames) as source:
                frames = [(t, image) for _, t, image in source]
            found = client.pose(frames[0][1], camera)  # one image: recognition + initial pose
            print(f"pose: found={found.found} t={found.pose.t if found.pose else None}")
            for msg in client.track(frames, camera):  # (time_s, image) pairs: the video's own times
                t = "-" if msg.pose is None else " ".join(f"{x:.2f}" for x in msg.pose.t)
                print(f"frame {msg.frame} {msg.status} t=[{t}] inliers {msg.inliers} {msg.latency_ms:.0f} ms")
    except QuatrackError as exc:  # the server's code, e.g. unknown_object, unauthorized, unreachable
        print(f"error: {exc.code}: {exc.message}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
