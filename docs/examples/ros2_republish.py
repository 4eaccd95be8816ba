"""Republish quatrack's tracked poses as a ROS 2 topic (geometry_msgs/PoseWithCovarianceStamped).

    quatrack serve &
    source /opt/ros/<distro>/setup.bash
    python docs/examples/ros2_republish.py --url http://127.0.0.1:8000 --mesh-unit cm --topic /quatrack/pose

The server converts (``?format=ros``): each answer's ``ros`` is the message as JSON, in metres,
quaternion ``x, y, z, w``, covariance row-major 6×6 over ``[x, y, z, rot X, rot Y, rot Z]``; this
script only fills a ``rclpy`` message from it. Without ``rclpy`` (or with ``--dry-run``) it prints
the JSON messages, one per line, instead of publishing. The stamp is the node's clock for a live
source (a camera, a stream: its ``time_s`` counts from its first frame, so the stamps started at
the 1970 epoch) and the frame's ``time_s`` for a video file; ``--now`` or ``--frame-time`` chooses.
A live source that stalls (``--stall-timeout``) or drops ends the run with a line on stderr and
exit status 1; an error is one line and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from quatrack.client import Client, QuatrackError
from quatrack.examples import example_dir
from quatrack.recognition.trackio import SourceError, open_frames


def publisher(topic: str, frame_id: str, now: bool):
    """A function publishing one ROS JSON message with rclpy (imported only here)."""
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped

    rclpy.init()
    node = rclpy.create_node("quatrack_republisher")
    pub = node.create_publisher(PoseWithCovarianceStamped, topic, 10)

    def publish(m: dict) -> None:
        out = PoseWithCovarianceStamped()
        if now:
            out.header.stamp = node.get_clock().now().to_msg()
        else:
            out.header.stamp.sec, out.header.stamp.nanosec = m["header"]["stamp"]["sec"], m["header"]["stamp"]["nanosec"]
        out.header.frame_id = frame_id
        p, o = m["pose"]["pose"]["position"], m["pose"]["pose"]["orientation"]
        out.pose.pose.position.x, out.pose.pose.position.y, out.pose.pose.position.z = p["x"], p["y"], p["z"]
        q = out.pose.pose.orientation
        q.x, q.y, q.z, q.w = o["x"], o["y"], o["z"], o["w"]
        out.pose.covariance = [float(c) for c in m["pose"]["covariance"]]
        pub.publish(out)

    return publish


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", default="http://127.0.0.1:8000")
    ap.add_argument("--token", default=None)
    ap.add_argument("--object", default="cookie-box")
    ap.add_argument("--mesh-unit", required=True, choices=["mm", "cm", "m"], help="the unit of the object's mesh")
    ap.add_argument("--video", default=None,
                    help="file, camera index (0) or device, or stream URL (default: the bundled video)")
    ap.add_argument("--camera", default=None, help="camera file (default: the bundled example's)")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--stall-timeout", type=float, default=None, metavar="S",
                    help="a camera or stream that gives no frame for S seconds has stalled: the run ends there, "
                         "saying so, exit status 1 (default 30)")
    ap.add_argument("--topic", default="/quatrack/pose")
    ap.add_argument("--frame-id", default="camera")
    stamp = ap.add_mutually_exclusive_group()
    stamp.add_argument("--now", action="store_true", default=None,
                       help="stamp with the ROS clock (the default for a camera or stream)")
    stamp.add_argument("--frame-time", dest="now", action="store_false",
                       help="stamp with the frame's time_s (the default for a video file; a live source's "
                            "counts from its first frame, i.e. from the 1970 epoch)")
    ap.add_argument("--dry-run", action="store_true", help="print the messages instead of publishing")
    args = ap.parse_args()
    example = example_dir("cookie-box")
    try:
        source = open_frames(video=args.video or str(example / "box.mp4"), max_frames=args.max_frames,
                             stall_timeout_s=args.stall_timeout)
    except SourceError as exc:  # (a file that is not there, a camera that does not open: one line)
        print(f"ros2_republish: error: {exc}", file=sys.stderr)
        return 2
    now = source.live if args.now is None else args.now
    publish = None
    if not args.dry_run:
        try:
            publish = publisher(args.topic, args.frame_id, now)
        except ImportError:
            print("ros2_republish: rclpy not found (source your ROS 2 setup); printing instead", file=sys.stderr)
    try:
        with Client(args.url, object=args.object, token=args.token) as client, source:
            frames = ((t, image) for _, t, image in source)  # (time_s, image): the stamps
            camera = args.camera or example / "camera.json"
            for msg in client.track(frames, camera, ros_mesh_unit=args.mesh_unit):
                if msg.ros is None:  # lost (or a frame the server could not read): nothing to publish
                    continue
                if publish is None:  # what would be published: the same frame_id and stamp
                    msg.ros["header"]["frame_id"] = args.frame_id
                    if now:
                        ns = time.time_ns()
                        msg.ros["header"]["stamp"] = {"sec": ns // 10**9, "nanosec": ns % 10**9}
                    print(json.dumps(msg.ros), flush=True)
                else:
                    publish(msg.ros)
    except QuatrackError as exc:
        print(f"ros2_republish: error: {exc.code}: {exc.message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 0
    if source.ended:  # (a stream that stalled or dropped: it ended with exit 0, without a word)
        print(f"ros2_republish: {source.label}: {source.ended}; stopped after {source.count} frames", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
