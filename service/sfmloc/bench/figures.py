"""PNG figures of a bench run (matplotlib, Agg backend, imported only here).

- ``per_frame``: the paper's Figure 2 for one sequence: detected / tracked / tracked-with-3D
  keypoints; per-frame time with guided (short grey bars) and global matching frames (tall
  black bars); position and orientation error.
- ``trajectory``: top view of the estimate against ground truth, lost frames marked.
- ``compare``: our engine and the peers on the same frames: error and per-frame time CDFs.
- ``throughput``: delivered rate, dropped fraction and latency against the client count.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..engine.types import Matching, Status
from ..eval.metrics import FrameRecord

COLORS = {"sfmloc": "tab:red", "global-every-frame": "tab:blue", "pycolmap-sift": "tab:green"}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _nan(x):
    return np.nan if x is None else x


def per_frame(records: list[FrameRecord], title: str, path: str | Path) -> Path:
    plt = _plt()
    idx = np.array([r.index for r in records])
    fig, axes = plt.subplots(
        3, 1, figsize=(11, 8.5), sharex=True, gridspec_kw={"height_ratios": [1, 1.2, 1]}
    )
    ax = axes[0]
    ax.plot(idx, [r.detected for r in records], color="0.55", lw=0.8, label="Detected")
    ax.plot(idx, [r.tracked for r in records], color="tab:blue", lw=0.9, label="Tracked")
    ax.plot(idx, [r.tracked_3d for r in records], color="tab:green", lw=0.9, label="Tracked-3D")
    ax.set_ylabel("keypoints")
    ax.legend(loc="upper right", ncol=3, fontsize=8, framealpha=0.9)
    ax.set_title(title, fontsize=11)

    ax = axes[1]
    t = np.array([r.latency_ms for r in records])
    top = max(60.0, float(np.percentile(t, 99)) * 1.3) if len(t) else 60.0
    guided = idx[[r.matching == Matching.GUIDED for r in records]]
    glob = idx[[r.matching == Matching.GLOBAL for r in records]]
    # Matching frames as bars in a band under the time axis (short grey: guided, tall black:
    # global), so they never hide the time curve.
    band = 0.16 * top
    ax.vlines(
        guided,
        -band,
        -band + 0.45 * band,
        color="0.55",
        lw=0.8,
        label=f"guided matching ({len(guided)})",
    )
    ax.vlines(
        glob, -band, -0.05 * band, color="black", lw=1.4, label=f"global matching ({len(glob)})"
    )
    ax.axhline(0, color="0.2", lw=0.6)
    ax.plot(idx, np.minimum(t, top), color="tab:red", lw=0.8, label="per-frame time")
    over = t > top
    if over.any():
        ax.plot(
            idx[over],
            np.full(over.sum(), top * 0.985),
            "v",
            color="tab:red",
            ms=4,
            label=f"clipped (max {t.max():.0f} ms)",
        )
    ax.axhline(1000 / 30, color="0.3", ls=":", lw=0.8, label="33 ms (30 Hz)")
    ax.set_ylim(-band, top)
    ax.set_yticks([v for v in ax.get_yticks() if 0 <= v <= top])
    ax.set_ylabel("time per frame (ms)")
    ax.legend(loc="upper right", ncol=3, fontsize=8, framealpha=0.9)

    ax = axes[2]
    pe = np.array([_nan(r.position_error_m) for r in records], float) * 100
    re_ = np.array([_nan(r.rotation_error_deg) for r in records], float)
    lost = np.array([r.status == Status.LOST for r in records])
    for i in idx[lost]:
        ax.axvspan(i - 0.5, i + 0.5, color="0.85", lw=0)
    ax.plot(idx, pe, color="tab:purple", lw=0.8, label="position error (cm)")
    ax.set_ylabel("position error (cm)", color="tab:purple")
    fin = pe[np.isfinite(pe)]
    ax.set_ylim(0, max(1.0, float(np.percentile(fin, 99)) * 1.3) if len(fin) else 1.0)
    ax2 = ax.twinx()
    ax2.plot(idx, re_, color="tab:orange", lw=0.8, label="orientation error (deg)")
    ax2.set_ylabel("orientation error (deg)", color="tab:orange")
    fr = re_[np.isfinite(re_)]
    ax2.set_ylim(0, max(0.5, float(np.percentile(fr, 99)) * 1.3) if len(fr) else 1.0)
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    if lost.any():
        import matplotlib.patches as mpatches

        h1.append(mpatches.Patch(color="0.85"))
        l1.append(f"lost ({int(lost.sum())})")
    ax.legend(h1 + h2, l1 + l2, loc="upper right", ncol=3, fontsize=8, framealpha=0.9)
    ax.set_xlabel("frame")
    ax.set_xlim(idx.min() - 1 if len(idx) else 0, idx.max() + 1 if len(idx) else 1)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def top_view_basis(gt_cam_from_world: list) -> tuple[np.ndarray, np.ndarray]:
    """Two world axes spanning the ground plane: "up" is opposite the cameras' mean image-down
    axis (hand-held and flying cameras stay roughly upright); the first axis is the main
    direction of travel within the plane."""
    down = np.mean([T.rotation[1] for T in gt_cam_from_world], axis=0)  # camera y axis in world
    up = -down / max(np.linalg.norm(down), 1e-9)
    C = np.array([T.center for T in gt_cam_from_world])
    P = C - np.outer(C @ up, up)
    P -= P.mean(0)
    _, _, vt = np.linalg.svd(P, full_matrices=False)
    a = vt[0] - (vt[0] @ up) * up
    a /= max(np.linalg.norm(a), 1e-9)
    b = np.cross(up, a)
    return a, b


def trajectory(
    records: list[FrameRecord], title: str, path: str | Path, points_xyz: np.ndarray | None = None
) -> Path:
    plt = _plt()
    gts = [r.gt_cam_from_world for r in records if r.gt_cam_from_world is not None]
    ests = [r.cam_from_world for r in records if r.cam_from_world is not None]
    # Without ground truth (a live stream) the estimates alone set the view.
    ref = gts if len(gts) >= 2 else ests
    fig, ax = plt.subplots(figsize=(8, 7))
    if len(ref) >= 2:
        a, b = top_view_basis(ref)
        G = np.array([T.center for T in ref])
        g2 = np.stack([G @ a, G @ b], 1)
        lo, hi = g2.min(0), g2.max(0)
        if points_xyz is not None and len(points_xyz):
            # Show the mapped area too (the paper draws the path over the reconstruction).
            p2 = np.stack([points_xyz @ a, points_xyz @ b], 1)
            lo = np.minimum(lo, np.percentile(p2, 5, axis=0))
            hi = np.maximum(hi, np.percentile(p2, 95, axis=0))
            pad = 0.05 * max(hi - lo) + 0.1
            inside = np.all((p2 > lo - pad) & (p2 < hi + pad), axis=1)
            p2 = p2[inside]
            if len(p2) > 20000:
                p2 = p2[np.random.default_rng(0).choice(len(p2), 20000, replace=False)]
            ax.scatter(
                p2[:, 0], p2[:, 1], s=1.0, c="0.7", lw=0, label="map points", rasterized=True
            )
        pad = 0.05 * max(hi - lo) + 0.1
        if len(gts) >= 2:
            ax.plot(g2[:, 0], g2[:, 1], color="black", lw=1.2, label="ground truth")
        est = [(r.cam_from_world.center, r.status) for r in records if r.cam_from_world is not None]
        if est:
            E = np.array([e[0] for e in est])
            e2 = np.stack([E @ a, E @ b], 1)
            ax.plot(
                e2[:, 0],
                e2[:, 1],
                ".",
                color="tab:red",
                ms=2.0,
                label=f"estimate ({len(est)} frames)",
            )
        lost = [
            r.gt_cam_from_world.center
            for r in records
            if r.status == Status.LOST and r.gt_cam_from_world is not None
        ]
        if lost:
            L = np.array(lost)
            ax.plot(
                L @ a,
                L @ b,
                "x",
                color="tab:blue",
                ms=3.5,
                mew=0.9,
                label=f"lost ({len(lost)} frames)",
            )
        ax.plot(*g2[0], "o", color="black", ms=6, mfc="white", label="start")
        if len(gts) < 2:
            ax.text(0.02, 0.98, "no ground truth", va="top", transform=ax.transAxes)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("m (top view, main direction of travel)")
    ax.set_ylabel("m")
    ax.set_title(title, fontsize=11)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize=8, markerscale=2, framealpha=0.9)
    else:
        ax.text(0.5, 0.5, "no ground truth", ha="center", va="center", transform=ax.transAxes)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _cdf(ax, values: np.ndarray, n_total: int, **kw) -> None:
    # A log axis cannot show 0: exact zeros (possible on synthetic data) sit at a small floor.
    v = np.maximum(np.sort(values[np.isfinite(values)]), 1e-4)
    if n_total == 0:
        return
    y = np.arange(1, len(v) + 1) / n_total * 100
    ax.step(
        np.concatenate([[v[0] if len(v) else 1e-3], v]),
        np.concatenate([[0], y]),
        where="post",
        **kw,
    )


def compare(
    methods: dict[str, list[FrameRecord]], summaries: dict[str, dict], title: str, path: str | Path
) -> Path:
    """Position error, rotation error and per-frame time CDFs of each method on the same
    frames (a frame without a pose never reaches 100%)."""
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    for name, recs in methods.items():
        s = summaries[name]
        c = COLORS.get(name, None)
        n = len(recs)
        pe = np.array([_nan(r.position_error_m) for r in recs], float) * 100
        re_ = np.array([_nan(r.rotation_error_deg) for r in recs], float)
        t = np.array([r.latency_ms for r in recs], float)
        _cdf(
            axes[0],
            pe,
            n,
            color=c,
            label=f"{name} (median {s['median_position_error_m'] * 100:.2f} cm)",
        )
        _cdf(
            axes[1],
            re_,
            n,
            color=c,
            label=f"{name} (median {s['median_rotation_error_deg']:.2f} deg)",
        )
        _cdf(axes[2], t, n, color=c, label=f"{name} (mean {s['T_ms_mean']:.1f} ms)")
    for ax, xl in zip(
        axes, ("position error (cm)", "orientation error (deg)", "time per frame (ms)")
    ):
        ax.set_xscale("log")
        ax.set_xlabel(xl + ", log scale")
        ax.set_ylabel("% of frames")
        ax.set_ylim(0, 101)
        ax.grid(alpha=0.3, which="both")
        ax.legend(loc="lower right", fontsize=8)
    axes[2].axvline(1000 / 30, color="0.3", ls=":", lw=0.8)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def throughput(rows: list[dict], title: str, path: str | Path) -> Path:
    plt = _plt()
    n = [r["clients"] for r in rows]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6))
    ax = axes[0]
    ax.plot(
        n, [r["offered_hz"] for r in rows], "--", color="0.5", label="offered (30 Hz per client)"
    )
    ax.plot(
        n,
        [r["delivered_hz_total"] for r in rows],
        "o-",
        color="tab:red",
        label="poses delivered, total",
    )
    ax.plot(
        n,
        [r["delivered_hz_per_client"] for r in rows],
        "s-",
        color="tab:blue",
        label="poses delivered, per client",
    )
    ax.set_xlabel("concurrent clients")
    ax.set_ylabel("poses per second")
    ax.set_xscale("log", base=2)
    ax.set_xticks(n, [str(v) for v in n])
    ax.grid(alpha=0.3)
    ax2 = ax.twinx()
    ax2.bar(
        n,
        [r["dropped_pct"] for r in rows],
        width=[v * 0.25 for v in n],
        color="0.8",
        alpha=0.6,
        label="dropped (%)",
        zorder=0,
    )
    ax2.set_ylabel("frames dropped (%)")
    ax2.set_ylim(0, 100)
    ax.set_zorder(ax2.get_zorder() + 1)
    ax.patch.set_visible(False)
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, loc="upper left", fontsize=8)
    ax = axes[1]
    ax.plot(
        n, [r["latency_ms_p50"] for r in rows], "o-", color="tab:green", label="p50 (median client)"
    )
    ax.plot(
        n, [r["latency_ms_p99"] for r in rows], "s-", color="tab:orange", label="p99 (worst client)"
    )
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xticks(n, [str(v) for v in n])
    ax.set_xlabel("concurrent clients")
    ax.set_ylabel("frame published -> pose received (ms)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
