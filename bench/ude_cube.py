"""`quatrack bench ude-cube`: Ude (1999), Section 5, reproduced literally.

One camera (480 lines × 640 pixels, image 6.6 mm × 8.8 mm, focal length 10 mm), a cube with
500 mm edges whose visible edges are the features, a constant-velocity trajectory, 6 s at 30 Hz.
End points get Gaussian noise (7 px along, 1 px across the segment), then are digitised.
The filter uses a = 2.0 mm²/s³, α = 0.0002 rad²/s³, and starts from a pose estimate of the first
image with zero velocities of variance 1e8.

Beside the Monte-Carlo errors it computes, along the true trajectory:
- the posterior Cramér–Rao bound (Tichavský et al. 1998) in the 12-D tangent coordinates,
  with the filter's plant noise (eq. 23) and with none (how the simulated truth moves);
- the filter's own linearised prediction of its *actual* error: the same gains, applied to a
  truth without plant noise and to the true measurement noise (including digitisation).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from quatrack.tracking import quaternion as quat
from quatrack.tracking.adjust import AdjustOptions, adjust, estimate_pose, spd_inverse
from quatrack.tracking.camera import PinholeCamera
from quatrack.tracking.measurements import SegmentMeasurements, project_model_points
from quatrack.tracking.motion import UdeConstantVelocity
from quatrack.tracking.propagation import plant_noise, predict_mean, transition_jacobian
from quatrack.tracking.state import FilterState, initial_state

# --- the experiment, as printed -------------------------------------------------------------
WIDTH, HEIGHT = 640, 480
SENSOR_W_MM, SENSOR_H_MM, FOCAL_MM = 8.8, 6.6, 10.0
EDGE_MM = 500.0
RATE_HZ, DURATION_S = 30.0, 6.0
SIGMA_ALONG_PX, SIGMA_ACROSS_PX = 7.0, 1.0
A_MM2_S3, ALPHA_RAD2_S3 = 2.0, 0.0002
VELOCITY_VARIANCE = 1e8
WINDOW = (3.0, 6.0)  # errors are averaged over 3 ≤ t ≤ 6

# Readings of the paper tried to explain where our figures and the paper's differ:
VARIANTS = {
    "paper": "the experiment as printed, in consistent full-angle units (the default)",
    "half-angle": "Ude's J_i and plant noise applied to his half-angle error u^q of eq. 16, literally",
    "isotropic-noise": "the filter assumes 7 px end-point noise in every direction (truth unchanged)",
    "silhouette-edges": "only the cube's outline edges are features, not its inner visible edges",
}

P0 = np.array([-300 * np.sqrt(3), 300 * np.sqrt(3), 2800.0])
V_TRUE = 100 * np.sqrt(3) * np.array([1.0, -1.0, 1.0])  # ‖v‖ = 300 mm/s
OMEGA_TRUE = np.pi / (12 * np.sqrt(3)) * np.array([1.0, 1.0, -1.0])  # ‖ω‖ = 15 °/s
Q0 = np.array([0.0, 0.8, -0.6, 0.0])

PAPER = {
    "position_mm": 1.65,
    "orientation_deg": 0.41,
    "velocity_mm_s": 0.86,
    "angular_velocity_deg_s": 0.37,
    "predicted_position_mm": 1.66,
    "predicted_orientation_deg": 0.42,
}
KEYS = tuple(PAPER)
# which 3-vector block of the 12-D error, in the posterior (False) or predicted (True) state
_BLOCKS = {
    "position_mm": (slice(0, 3), False, 1.0),
    "orientation_deg": (slice(3, 6), False, np.degrees(1.0)),
    "velocity_mm_s": (slice(6, 9), False, 1.0),
    "angular_velocity_deg_s": (slice(9, 12), False, np.degrees(1.0)),
    "predicted_position_mm": (slice(0, 3), True, 1.0),
    "predicted_orientation_deg": (slice(3, 6), True, np.degrees(1.0)),
}


@dataclass(frozen=True)
class HalfAngleReading(UdeConstantVelocity):
    """Eqs. 22–23 applied, as printed, to a covariance kept in half-angle units ``r = δθ/2``
    (Ude's eq. 16). In full-angle units that doubles ``G`` and the α-terms' couplings: a
    deliberately literal reading, only to test whether it explains the paper's figures."""

    def predict(self, state, dt):
        p, q, v, w = predict_mean(state.p, state.q, state.v, state.omega, dt)
        T = np.diag([1.0, 1, 1, 2, 2, 2, 1, 1, 1, 1, 1, 1])  # r → δθ
        Ti = np.linalg.inv(T)
        J = transition_jacobian(state.omega, dt)
        S_half = J @ (Ti @ state.covariance @ Ti) @ J.T + plant_noise(dt, self.a, self.alpha)
        S = T @ S_half @ T
        return FilterState(state.t + dt, p, q, v, w, 0.5 * (S + S.T))


def camera() -> PinholeCamera:
    """f = 10 mm on 13.75 µm square pixels: fx = fy = 727.27 px; principal point at the centre."""
    f_px = FOCAL_MM / (SENSOR_W_MM / WIDTH)
    assert np.isclose(f_px, FOCAL_MM / (SENSOR_H_MM / HEIGHT))
    return PinholeCamera(f_px, f_px, WIDTH / 2, HEIGHT / 2, width=WIDTH, height=HEIGHT)


def cube() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (8, 3), edges (12, 2) as vertex indices, and for each edge its two face normals."""
    h = EDGE_MM / 2
    V = np.array([[x, y, z] for x in (-h, h) for y in (-h, h) for z in (-h, h)])
    edges = np.array([(i, j) for i in range(8) for j in range(i + 1, 8) if np.sum(V[i] != V[j]) == 1])
    normals = np.empty((12, 2, 3))
    for k, (i, j) in enumerate(edges):
        axes = [a for a in range(3) if V[i, a] == V[j, a]]  # the two constant coordinates
        for m, a in enumerate(axes):
            normals[k, m] = np.eye(3)[a] * np.sign(V[i, a])
    return V, edges, normals


def truth(t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """``p(t) = P0 + t v`` (mm) and ``q(t) = exp(t ω / 2) * q0``."""
    t = np.asarray(t, dtype=float)
    return P0 + t[..., None] * V_TRUE, quat.multiply(quat.exp(0.5 * t[..., None] * OMEGA_TRUE), Q0)


def visible_edges(p: np.ndarray, q: np.ndarray, outline_only: bool = False) -> np.ndarray:
    """Indices of edges on at least one face turned towards the camera (or, with
    ``outline_only``, on exactly one: the silhouette)."""
    _, _, normals = cube()
    R = quat.to_matrix(q)
    n_cam = normals @ R.T
    centre = n_cam * (EDGE_MM / 2) + p  # a point on each face, camera frame
    facing = np.einsum("kij,kij->ki", n_cam, centre) < 0
    return np.flatnonzero(facing.sum(axis=1) == 1 if outline_only else facing.any(axis=1))


@dataclass
class Frame:
    segments: SegmentMeasurements
    endpoints: np.ndarray  # (n, 2, 2) digitised, as measured
    model_segments: np.ndarray  # (n, 2, 3)


def simulate_frame(rng: np.random.Generator, t: float, cam: PinholeCamera, variant: str = "paper") -> Frame:
    """Noisy, digitised image segments of the visible cube edges at time ``t``."""
    V, edges, _ = cube()
    p, q = truth(t)
    idx = visible_edges(p, q, outline_only=variant == "silhouette-edges")
    segs = V[edges[idx]]  # (n, 2, 3)
    uv = cam.project(segs.reshape(-1, 3) @ quat.to_matrix(q).T + p).reshape(-1, 2, 2)
    d = uv[:, 1] - uv[:, 0]
    along = d / np.linalg.norm(d, axis=-1, keepdims=True)
    across = np.stack([-along[:, 1], along[:, 0]], -1)
    noise_a = rng.normal(0.0, SIGMA_ALONG_PX, size=(len(idx), 2, 1))
    noise_c = rng.normal(0.0, SIGMA_ACROSS_PX, size=(len(idx), 2, 1))
    noisy = uv + noise_a * along[:, None, :] + noise_c * across[:, None, :]
    digitised = np.round(noisy)
    assumed_across = SIGMA_ALONG_PX if variant == "isotropic-noise" else SIGMA_ACROSS_PX
    meas = SegmentMeasurements.from_endpoints(cam, segs, digitised, SIGMA_ALONG_PX, assumed_across)
    return Frame(meas, digitised, segs)


def initial_pose(frame: Frame, cam: PinholeCamera):
    """Pose estimate from the first image: PnP on the segments' end points as a start, then
    Gauss–Newton on the segment measurements alone, whose ``(DᵀD)⁻¹`` is the covariance."""
    X = frame.model_segments.reshape(-1, 3)
    uv = frame.endpoints.reshape(-1, 2)
    ok, rvec, tvec = cv2.solvePnP(X, uv, cam.matrix, None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise RuntimeError("PnP failed on the first frame")
    return estimate_pose([frame.segments], tvec.ravel(), quat.from_rotvec(rvec.ravel()))


@dataclass
class SeedRun:
    errors: dict[str, np.ndarray]  # per frame in the window
    sq_errors: dict[str, np.ndarray]
    filter_var: dict[str, np.ndarray]  # trace of the filter's own covariance block, per frame
    adjust_s: np.ndarray
    predict_s: np.ndarray
    iterations: np.ndarray
    table: tuple = ()
    final_gradient_sq: np.ndarray = field(default_factory=lambda: np.empty(0))


def frame_times() -> np.ndarray:
    return np.arange(int(round(DURATION_S * RATE_HZ)) + 1) / RATE_HZ


def run_seed(
    seed: int, table_frame: int | None = None, options: AdjustOptions | None = None, variant: str = "paper"
) -> SeedRun:
    """One Monte-Carlo run of the experiment."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; expected one of {sorted(VARIANTS)}")
    rng = np.random.default_rng(seed)
    cam = camera()
    times = frame_times()
    model_cls = HalfAngleReading if variant == "half-angle" else UdeConstantVelocity
    model = model_cls(a=A_MM2_S3, alpha=ALPHA_RAD2_S3)
    options = options or AdjustOptions()
    first = simulate_frame(rng, times[0], cam, variant)
    est = initial_pose(first, cam)
    state = initial_state(times[0], est.p, est.q, est.covariance, velocity_variance=VELOCITY_VARIANCE)
    in_window = (times >= WINDOW[0] - 1e-9) & (times <= WINDOW[1] + 1e-9)
    errors = {k: [] for k in KEYS}
    sq = {k: [] for k in KEYS}
    var = {k: [] for k in KEYS}
    adjust_s, predict_s, iters, gsq = [], [], [], []
    table = ()
    for k in range(1, len(times)):
        frame = simulate_frame(rng, times[k], cam, variant)
        t0 = time.perf_counter()
        prior = model.predict(state, times[k] - state.t)
        t1 = time.perf_counter()
        opts = options if k != table_frame else AdjustOptions(**{**options.__dict__, "record": True})
        result = adjust(prior, [frame.segments], opts)
        t2 = time.perf_counter()
        state = result.state
        predict_s.append(t1 - t0)
        adjust_s.append(t2 - t1)
        iters.append(result.iterations)
        gsq.append(result.final_gradient_norm_sq)
        if k == table_frame:
            table = result.history + (result.final_gradient_norm_sq,)
        if not in_window[k]:
            continue
        p_true, q_true = truth(times[k])
        err = {
            "position_mm": state.p - p_true,
            "orientation_deg": np.degrees(quat.to_rotvec(quat.multiply(q_true, quat.conjugate(state.q)))),
            "velocity_mm_s": state.v - V_TRUE,
            "angular_velocity_deg_s": np.degrees(state.omega - OMEGA_TRUE),
            "predicted_position_mm": prior.p - p_true,
            "predicted_orientation_deg": np.degrees(quat.to_rotvec(quat.multiply(q_true, quat.conjugate(prior.q)))),
        }
        for key, e in err.items():
            sl, predicted, scale = _BLOCKS[key]
            errors[key].append(np.linalg.norm(e))
            sq[key].append(float(e @ e))
            S = prior.covariance if predicted else state.covariance
            var[key].append(float(np.trace(S[sl, sl])) * scale**2)
    return SeedRun(
        {k: np.array(v) for k, v in errors.items()},
        {k: np.array(v) for k, v in sq.items()},
        {k: np.array(v) for k, v in var.items()},
        np.array(adjust_s),
        np.array(predict_s),
        np.array(iters),
        table,
        np.array(gsq),
    )


@dataclass
class _Linearised:
    """One frame's measurement model at the true pose."""

    H_true: np.ndarray  # (m, 12), whitened by the true nominal noise: HᵀH is the Fisher information
    H_filter: np.ndarray  # (m, 12), whitened by the noise the filter assumes
    R_filter: np.ndarray  # (m, m), the true noise (with digitisation) in the filter's whitened units


def _linearise(cam: PinholeCamera, t: float, variant: str) -> _Linearised:
    V, edges, _ = cube()
    p, q = truth(t)
    R = quat.to_matrix(q)
    segs = V[edges[visible_edges(p, q, outline_only=variant == "silhouette-edges")]]
    uv, _ = project_model_points(cam, segs.reshape(-1, 3), p, R, jacobian=False)
    uv = uv.reshape(-1, 2, 2)
    assumed_across = SIGMA_ALONG_PX if variant == "isotropic-noise" else SIGMA_ACROSS_PX
    H = []
    for across in (SIGMA_ACROSS_PX, assumed_across):
        meas = SegmentMeasurements.from_endpoints(cam, segs, uv, SIGMA_ALONG_PX, across)
        J = np.zeros((3 * len(meas), 12))
        J[:, :6] = meas.linearize(p, R).jacobian.reshape(-1, 6)
        H.append(J)
    # True noise: the stated end-point noise plus digitisation (uniform, 1/12 px² per axis),
    # carried to [x_m, y_m, θ] to first order, then whitened as the filter does.
    d = uv[:, 1] - uv[:, 0]
    length = np.linalg.norm(d, axis=-1)
    al = d / length[:, None]
    ac = np.stack([-al[:, 1], al[:, 0]], -1)
    C_end = SIGMA_ALONG_PX**2 * al[:, :, None] * al[:, None, :] + SIGMA_ACROSS_PX**2 * ac[:, :, None] * ac[:, None, :]
    C_end = C_end + np.eye(2) / 12.0
    n = len(segs)
    Rf = np.zeros((3 * n, 3 * n))
    for i in range(n):
        Jy = np.zeros((3, 4))  # ∂[x_m, y_m, θ]/∂[u1, u2]
        Jy[:2, :2] = Jy[:2, 2:] = 0.5 * np.eye(2)
        g = np.array([-d[i, 1], d[i, 0]]) / length[i] ** 2
        Jy[2, :2], Jy[2, 2:] = -g, g
        C = np.zeros((4, 4))
        C[:2, :2] = C[2:, 2:] = C_end[i]
        W = meas.sqrt_info[i]
        Rf[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = W @ Jy @ C @ Jy.T @ W.T
    return _Linearised(H[0], H[1], Rf)


@dataclass
class Bounds:
    """Per-frame covariances (12×12) along the true trajectory: posterior and predicted."""

    crb: np.ndarray
    crb_pred: np.ndarray
    crb_free: np.ndarray  # no plant noise
    crb_free_pred: np.ndarray
    actual_msq: np.ndarray  # E[e eᵀ] of the filter's actual error (mean included), posterior
    actual_msq_pred: np.ndarray


def bounds(variant: str = "paper") -> Bounds:
    """PCRB with and without plant noise, and the filter's linearised actual-error prediction.

    The bounds start from the Fisher information of the first image about the pose, and 1e-8
    about the velocities (the filter's start). In covariance form the Tichavský recursion for
    additive Gaussian noise reads ``P⁻ = F P Fᵀ + Q``, ``P = (P⁻⁻¹ + HᵀH)⁻¹``; with ``Q = 0`` it is
    the information about a deterministic trajectory (the simulated truth). The bounds use the
    true noise; the filter's recursion uses what the variant's filter assumes, and its actual
    error is carried with the true dynamics (no plant noise) and the true measurement noise.
    """
    cam = camera()
    times = frame_times()
    T = np.diag([1.0, 1, 1, 2, 2, 2, 1, 1, 1, 1, 1, 1])  # half-angle r → δθ, for that variant

    def filter_transition(F: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if variant == "half-angle":
            return T @ F @ np.linalg.inv(T), T @ Q @ T
        return F, Q

    lin0 = _linearise(cam, times[0], variant)
    P0 = np.zeros((12, 12))
    P0[:6, :6] = spd_inverse(lin0.H_true[:, :6].T @ lin0.H_true[:, :6])
    P0[6:, 6:] = VELOCITY_VARIANCE * np.eye(6)
    P, Pf = P0.copy(), P0.copy()
    Pfil = P0.copy()
    Pfil[:6, :6] = spd_inverse(lin0.H_filter[:, :6].T @ lin0.H_filter[:, :6])
    # the filter's actual error: mean m (the initial velocity guess 0 is off by the truth) and
    # covariance Pa; the initial pose error is that of the first image's estimate.
    m = np.concatenate([np.zeros(6), -V_TRUE, -OMEGA_TRUE])
    K0 = Pfil[:6, :6] @ lin0.H_filter[:, :6].T
    Pa = np.zeros((12, 12))
    Pa[:6, :6] = K0 @ lin0.R_filter @ K0.T
    out = {k: [] for k in ("crb", "crb_pred", "crb_free", "crb_free_pred", "actual", "actual_pred")}
    for k in range(1, len(times)):
        dt = times[k] - times[k - 1]
        F = transition_jacobian(OMEGA_TRUE, dt)
        Q = plant_noise(dt, A_MM2_S3, ALPHA_RAD2_S3)
        lin = _linearise(cam, times[k], variant)
        info = lin.H_true.T @ lin.H_true
        P_pred = F @ P @ F.T + Q  # with plant noise
        P = spd_inverse(spd_inverse(P_pred) + info)
        Pf_pred = F @ Pf @ F.T  # without
        Pf = spd_inverse(spd_inverse(Pf_pred) + info)
        # the filter's covariance recursion, linearised at the truth, gives its gain
        F_fil, Q_fil = filter_transition(F, Q)
        Pfil = spd_inverse(spd_inverse(F_fil @ Pfil @ F_fil.T + Q_fil) + lin.H_filter.T @ lin.H_filter)
        K = Pfil @ lin.H_filter.T
        # actual error: e⁻ = F e (the truth has no plant noise); e = (I - K H) e⁻ + K n
        m_pred = F @ m
        Pa_pred = F @ Pa @ F.T
        IKH = np.eye(12) - K @ lin.H_filter
        m = IKH @ m_pred
        Pa = IKH @ Pa_pred @ IKH.T + K @ lin.R_filter @ K.T
        out["crb"].append(P)
        out["crb_pred"].append(P_pred)
        out["crb_free"].append(Pf)
        out["crb_free_pred"].append(Pf_pred)
        out["actual"].append(Pa + np.outer(m, m))
        out["actual_pred"].append(Pa_pred + np.outer(m_pred, m_pred))
    a = {k: np.array(v) for k, v in out.items()}
    return Bounds(a["crb"], a["crb_pred"], a["crb_free"], a["crb_free_pred"], a["actual"], a["actual_pred"])


def _rms_of(covs: np.ndarray, key: str, window: np.ndarray) -> float:
    """``sqrt(mean over the window of trace(block))`` in the key's units."""
    sl, _, scale = _BLOCKS[key]
    return float(np.sqrt(np.mean(np.trace(covs[window][:, sl, sl], axis1=1, axis2=2))) * scale)


def run(
    seeds: int = 20, first_seed: int = 0, table_frame: int = 90, progress: bool = True, variant: str = "paper"
) -> dict:
    """The whole benchmark: ``seeds`` runs, bounds, timings. Returns a JSON-ready summary.

    The bounds follow the variant's features and true noise; the linearised prediction follows
    the variant's filter."""
    from tqdm import tqdm

    if seeds < 2:
        raise ValueError("need at least 2 seeds for a spread")
    runs = []
    for s in tqdm(range(first_seed, first_seed + seeds), desc="ude-cube seeds", disable=not progress, unit="seed"):
        runs.append(run_seed(s, table_frame=table_frame if s == first_seed else None, variant=variant))
    b = bounds(variant)
    times = frame_times()[1:]
    window = (times >= WINDOW[0] - 1e-9) & (times <= WINDOW[1] + 1e-9)
    summary: dict = {"seeds": seeds, "frames": int(len(times) + 1), "variant": variant}
    crb, crb_free, per_seed, filt, actual = {}, {}, {}, {}, {}
    for key in KEYS:
        predicted = _BLOCKS[key][1]
        seed_means = np.array([r.errors[key].mean() for r in runs])
        rms = float(np.sqrt(np.mean([r.sq_errors[key].mean() for r in runs])))
        summary[key] = float(seed_means.mean())
        per_seed[key] = {
            "mean": float(seed_means.mean()),
            "sd": float(seed_means.std(ddof=1)),
            "min": float(seed_means.min()),
            "max": float(seed_means.max()),
            "paper": PAPER[key],
            "paper_percentile": float(100.0 * np.mean(seed_means < PAPER[key])),
            "rms": rms,
        }
        crb[key] = rms / _rms_of(b.crb_pred if predicted else b.crb, key, window)
        crb_free[key] = rms / _rms_of(b.crb_free_pred if predicted else b.crb_free, key, window)
        filt[key] = rms / float(np.sqrt(np.mean([r.filter_var[key].mean() for r in runs])))
        actual[key] = rms / _rms_of(b.actual_msq_pred if predicted else b.actual_msq, key, window)
        per_seed[key]["filter_sigma_vs_crb"] = float(
            np.sqrt(np.mean([r.filter_var[key].mean() for r in runs]))
            / _rms_of(b.crb_pred if predicted else b.crb, key, window)
        )
    adjust_ms = np.concatenate([r.adjust_s for r in runs]) * 1e3
    predict_ms = np.concatenate([r.predict_s for r in runs]) * 1e3
    iters = np.concatenate([r.iterations for r in runs])
    gsq = np.concatenate([r.final_gradient_sq for r in runs])
    summary.update(
        crb_ratio=crb,
        crb_ratio_no_plant_noise=crb_free,
        filter_covariance_ratio=filt,
        linearised_prediction_ratio=actual,
        per_seed=per_seed,
        adjust_ms_p50=float(np.percentile(adjust_ms, 50)),
        adjust_ms_p95=float(np.percentile(adjust_ms, 95)),
        predict_ms_p50=float(np.percentile(predict_ms, 50)),
        predict_ms_p95=float(np.percentile(predict_ms, 95)),
        iterations=float(iters.mean()),
        iterations_max=int(iters.max()),
        final_gradient_norm_sq_max=float(gsq.max()),
        table1_frame=table_frame,
        table1=[
            [row.step_p, row.step_theta, row.step_v, row.step_omega, row.gradient_norm_sq]
            for row in runs[0].table[:-1]
        ]
        + [[None, None, None, None, runs[0].table[-1]]],
    )
    return summary


_LABELS = {
    "position_mm": ("position", "mm"),
    "orientation_deg": ("orientation", "deg"),
    "velocity_mm_s": ("linear velocity", "mm/s"),
    "angular_velocity_deg_s": ("angular velocity", "deg/s"),
    "predicted_position_mm": ("predicted position", "mm"),
    "predicted_orientation_deg": ("predicted orientation", "deg"),
}


def format_report(s: dict) -> str:
    """A human-readable report of :func:`run`'s summary."""
    lines = [
        f"Ude (1999) cube experiment, {s['seeds']} seeds x {s['frames']} frames; errors averaged over 3 <= t <= 6 s",
        f"variant: {s['variant']} ({VARIANTS[s['variant']]})",
        "",
        f"{'':24s}{'mean ± sd (seeds)':>22s}{'paper':>8s}{'paper pct':>10s}"
        f"{'/PCRB':>8s}{'/PCRB0':>8s}{'/filter':>9s}{'/lin.pred':>10s}",
    ]
    for key in KEYS:
        label, unit = _LABELS[key]
        d = s["per_seed"][key]
        lines.append(
            f"{label + ' (' + unit + ')':24s}{d['mean']:>12.3f} ± {d['sd']:<7.3f}{d['paper']:>8.2f}"
            f"{d['paper_percentile']:>9.0f}%{s['crb_ratio'][key]:>8.2f}{s['crb_ratio_no_plant_noise'][key]:>8.2f}"
            f"{s['filter_covariance_ratio'][key]:>9.2f}{s['linearised_prediction_ratio'][key]:>10.2f}"
        )
    lines += [
        "",
        "ratios are RMS error / sqrt(mean trace of the covariance block): PCRB with the filter's plant",
        "noise, PCRB0 without (the bound for any estimator of this truth), the filter's own covariance,",
        "and the filter's linearised prediction of its actual error.",
        "",
        f"Table 1 (seed {0}, frame {s['table1_frame']}):",
        f"{'|dp|':>14s}{'2|dr|=|dθ|':>14s}{'|dv|':>14s}{'|dω|':>14s}{'|∇F|²':>14s}",
    ]
    for row in s["table1"]:
        lines.append("".join(f"{'':>14s}" if x is None else f"{x:>14.6e}" for x in row))
    lines += [
        "",
        f"adjustment: p50 {s['adjust_ms_p50']:.3f} ms, p95 {s['adjust_ms_p95']:.3f} ms, "
        f"{s['iterations']:.2f} Gauss-Newton iterations per frame (max {s['iterations_max']}), "
        f"final |∇F|² <= {s['final_gradient_norm_sq_max']:.1e}",
        f"prediction: p50 {s['predict_ms_p50']:.3f} ms, p95 {s['predict_ms_p95']:.3f} ms",
    ]
    return "\n".join(lines)


def main(seeds: int, first_seed: int, table_frame: int, as_json: bool, variant: str = "paper") -> int:
    summary = run(seeds=seeds, first_seed=first_seed, table_frame=table_frame, progress=not as_json, variant=variant)
    print(json.dumps(summary) if as_json else format_report(summary))
    return 0
