"""The README's library example runs as written and does what it says."""

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def test_library_example_runs_and_recovers_the_motion(capsys):
    text = README.read_text(encoding="utf-8")
    section = text[text.index("## The tracker as a library"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    scope: dict = {}
    exec(compile(code, "README.md", "exec"), scope)  # noqa: S102 - our own documentation
    s = scope["s"]
    np.testing.assert_allclose(s.v, [40.0, 0.0, 0.0], atol=0.5)  # mm/s, as the example moves it
    np.testing.assert_allclose(s.omega, [0.0, 0.3, 0.0], atol=0.01)  # rad/s
    # the printed lines are the state's pose, velocities and 1σ, as the comments say
    lines = capsys.readouterr().out.splitlines()
    assert lines == [f"{s.pose} {s.v.round(1)} {s.omega.round(3)}", str(np.sqrt(np.diag(s.pose_covariance)).round(4))]
    assert lines[0].startswith("Pose(q_wxyz=[")
    sigma = np.array(lines[1].strip("[]").split(), float)
    assert sigma.shape == (6,) and np.all(sigma > 0) and np.all(sigma[:3] < 5.0) and np.all(sigma[3:] < 0.05)


def test_the_finding_and_tracking_example_runs_and_its_conversions_agree(capsys):
    from scipy.spatial.transform import Rotation

    text = README.read_text(encoding="utf-8")
    section = text[text.index("### Finding and tracking a trained object"):]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    scope: dict = {}
    try:
        exec(compile(code, "README.md", "exec"), scope)  # noqa: S102 - our own documentation
    finally:
        if "store" in scope:
            import shutil

            shutil.rmtree(scope["store"], ignore_errors=True)
    found, step = scope["found"], scope["step"]
    assert found.found and step.status == "tracking"
    assert 60 < np.linalg.norm(step.pose.t) < 80  # (cm: the box is about 70 cm away)
    R = Rotation.from_quat(scope["q_xyzw"]).as_matrix()
    np.testing.assert_allclose(R, scope["T"][:3, :3], atol=1e-12)
    np.testing.assert_allclose(scope["T"][:3, 3], step.t)
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("True Pose(q_wxyz=[") and lines[1].startswith("tracking [")


def test_the_table_of_contents_links_every_section_and_only_sections():
    """Each ## / ### heading is listed, and each link reaches a heading (GitHub's anchors: lower
    case, punctuation dropped, spaces as hyphens): a renamed heading breaks no link unseen."""
    text = README.read_text(encoding="utf-8")

    def anchor(title: str) -> str:
        return re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")

    heads = [anchor(t) for t in re.findall(r"^#{2,3} (.+)$", text, re.M)]
    links = re.findall(r"^\s*- \[[^\]]+\]\(#([^)]+)\)$", text, re.M)
    assert links == heads
