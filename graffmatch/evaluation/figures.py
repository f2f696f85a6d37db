"""The evaluation's figures: LMR curves, error heatmaps, runtimes, rho, validity, dataset.

Matplotlib is imported lazily (Agg backend) so that the tables never need it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from graffmatch.evaluation import metrics as M
from graffmatch.evaluation import validity as V
from graffmatch.evaluation.records import GT_METHOD
from graffmatch.evaluation.tables import group_by, num

if TYPE_CHECKING:
    from graffmatch.evaluation.loop_closure_dataset import LoopClosureDataset


# ----------------------------------------------------------------------------------------------
# figures
# ----------------------------------------------------------------------------------------------
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _oirs(group: Sequence[Mapping[str, Any]]) -> np.ndarray:
    tau = num(group[0].get("tau_d_deg", M.DEFAULT_TAU_D_DEG))
    return np.array([M.PairRecord.from_dict(r).oir(tau) for r in group])


def fig_lmr(records: Sequence[Mapping[str, Any]], methods: Sequence[str], path: Path, title: str):
    """LMR vs tau_OIR (left) and LMR at tau_OIR = 0.8 vs tau_d (right)."""
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.5))
    groups = group_by(records, "method")
    for m in methods:
        g = groups.get((m,))
        if not g:
            continue
        style = {"color": "k", "ls": "--"} if m == GT_METHOD else {}
        t, v = M.lmr_curve(_oirs(g))
        a1.plot(t, v, label=f"{m} (AUC {np.mean(_oirs(g)):.2f})", **style)
        dists = [M.PairRecord.from_dict(r).association_distances_deg for r in g]
        td, vd = M.lmr_vs_tau_d(dists)
        a2.plot(td, vd, label=m, **style)
    a1.set(xlabel=r"$\tau_{OIR}$", ylabel="LMR", title=f"{title}: LMR vs $\\tau_{{OIR}}$")
    a2.set(
        xlabel=r"$\tau_d$ [deg]",
        ylabel=r"LMR at $\tau_{OIR}=0.8$",
        title=f"{title}: LMR vs $\\tau_d$",
    )
    a2.axvline(M.DEFAULT_TAU_D_DEG, color="gray", lw=0.8)
    for a in (a1, a2):
        a.set_ylim(-0.02, 1.02)
        a.grid(alpha=0.3)
    a1.legend(fontsize=7, loc="lower left")
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.12, top=0.92, wspace=0.18)
    fig.savefig(path, dpi=110)
    plt.close(fig)


ROT_RANGE = (-2.0, 2.5)  # log10 deg
TRANS_RANGE = (-2.5, 2.0)  # log10 m


def fig_error_heatmaps(
    records: Sequence[Mapping[str, Any]], methods: Sequence[str], path: Path, title: str
) -> None:
    """Alignment-error densities: rows = cases, columns = methods (GT-matches first).

    Each panel is a 2D histogram of log10 translation error (x, -2.5..2) vs log10 rotation
    error (y, -2..2.5), divided by its maximum ("likelihood-normalised"); cyan lines mark
    5 deg and 1 m; pairs without an estimate are counted under the panel. The panels are tiled
    into one image on one axes: dozens of matplotlib axes would dominate the report's runtime.
    """
    plt = _plt()
    cases = sorted({r["case"] for r in records}, key=str)
    groups = group_by(records, "case", "method")
    nr, nc, nb, gap = len(cases), len(methods), 30, 6
    bins = (np.linspace(*TRANS_RANGE, nb + 1), np.linspace(*ROT_RANGE, nb + 1))
    img = np.full((nr * (nb + gap), nc * (nb + gap)), np.nan)
    labels = []
    for i, case in enumerate(cases):
        for j, m in enumerate(methods):
            g = groups.get((case, m), [])
            rot = np.array([num(r["rotation_error_deg"]) for r in g])
            tr = np.array([num(r["translation_error_m"]) for r in g])
            fin = np.isfinite(rot) & np.isfinite(tr)
            x = np.clip(np.log10(np.maximum(tr[fin], 1e-9)), *TRANS_RANGE)
            y = np.clip(np.log10(np.maximum(rot[fin], 1e-9)), *ROT_RANGE)
            H, _, _ = np.histogram2d(x, y, bins=bins)
            if H.max() > 0:
                H = H / H.max()  # likelihood-normalised: the densest cell is 1
            r0, c0 = i * (nb + gap), j * (nb + gap)
            img[r0 : r0 + nb, c0 : c0 + nb] = H.T[::-1]  # rows: high rotation error on top
            ok = sum(bool(r["success"]) for r in g)
            labels.append(
                (r0 + nb + 0.5, c0 + nb / 2, f"{ok}/{len(g)} ok, {int((~fin).sum())} none")
            )
    fig, ax = plt.subplots(figsize=(1.45 * nc + 1.0, 1.55 * nr + 1.0))
    fig.subplots_adjust(left=0.8 / (1.45 * nc + 1.0), right=0.99, bottom=0.02, top=0.86)
    cmap = plt.get_cmap("magma").with_extremes(bad="white")
    ax.imshow(img, cmap=cmap, vmin=0, vmax=1, interpolation="nearest", aspect="equal")
    # threshold lines: x = log10(1 m), y = log10(5 deg), in bin units of each panel
    xt = (0.0 - TRANS_RANGE[0]) / (TRANS_RANGE[1] - TRANS_RANGE[0]) * nb - 0.5
    yt = nb - (np.log10(5.0) - ROT_RANGE[0]) / (ROT_RANGE[1] - ROT_RANGE[0]) * nb - 0.5
    for i in range(nr):
        for j in range(nc):
            r0, c0 = i * (nb + gap), j * (nb + gap)
            ax.plot([c0 + xt] * 2, [r0 - 0.5, r0 + nb - 0.5], color="c", lw=0.6)
            ax.plot([c0 - 0.5, c0 + nb - 0.5], [r0 + yt] * 2, color="c", lw=0.6)
    for r, c, text in labels:
        ax.text(c, r, text, ha="center", va="top", fontsize=5.5)
    for j, m in enumerate(methods):
        ax.text(j * (nb + gap) + nb / 2, -1.5, m, ha="center", va="bottom", fontsize=6.5)
    for i, case in enumerate(cases):
        ax.text(
            -2,
            i * (nb + gap) + nb / 2,
            f"case {case}",
            ha="right",
            va="center",
            fontsize=7,
            rotation=90,
        )
    ax.set_axis_off()
    ax.set_xlim(-4, img.shape[1])
    ax.set_ylim(img.shape[0], -4)
    fig.suptitle(
        f"{title}: alignment-error density per method (columns) and case (rows)\n"
        "x: log10 t_e [m] from -2.5 to 2, y: log10 R_e [deg] from -2 to 2.5; cyan: 1 m, 5 deg",
        fontsize=7,
    )
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fig_runtimes(records: Sequence[Mapping[str, Any]], methods: Sequence[str], out: Path) -> None:
    """Box plots of total runtime per method, and of each stage of each method (one axes)."""
    plt = _plt()
    groups = group_by(records, "method")

    def box(path: Path, series: list[tuple[str, list[float]]], ylabel: str, title: str) -> None:
        fig, ax = plt.subplots(figsize=(max(6.0, 0.32 * len(series) + 2), 4.8))
        fig.subplots_adjust(left=0.12, right=0.99, bottom=0.3, top=0.92)
        if series:
            ax.boxplot([v for _, v in series], showfliers=False)
            ax.set_xticks(
                range(1, len(series) + 1),
                [k for k, _ in series],
                rotation=60,
                ha="right",
                fontsize=6.5,
            )
            ax.set_yscale("log")
        ax.axhline(100.0, color="gray", ls=":", lw=0.8)  # 10 Hz LiDAR budget
        ax.set_ylabel(ylabel)
        ax.set_title(title, fontsize=9)
        fig.savefig(path, dpi=110)
        plt.close(fig)

    def ms(g: Sequence[Mapping[str, Any]], stage: str) -> list[float]:
        v = [1e3 * num(r["timings"].get(stage)) for r in g if stage in r["timings"]]
        return [max(x, 1e-3) for x in v if np.isfinite(x)]

    totals = [(m, ms(groups.get((m,), []), "total")) for m in methods]
    box(
        out / "runtime_total.png",
        [(m, v) for m, v in totals if v],
        "total runtime per pair [ms] (log)",
        "Runtime per method (dotted: 100 ms = 10 Hz)",
    )
    stages: list[tuple[str, list[float]]] = []
    for m in methods:
        g = groups.get((m,), [])
        names = sorted({k for r in g for k in r["timings"] if k != "total"})
        stages += [(f"{m}: {s}", v) for s in names if (v := ms(g, s))]
    if stages:
        box(
            out / "runtime_stages.png",
            stages,
            "stage runtime [ms] (log)",
            "Runtime per method and stage",
        )


def fig_rho(rho_rows: Sequence[Mapping[str, Any]], stats: Mapping[str, Any], path: Path) -> None:
    """Histogram of pairwise landmark-centroid distances (left) and AUC over rho (right)."""
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    for suite, st in stats.items():
        counts = np.asarray(st.get("counts", []), dtype=float)
        if counts.sum() <= 0:
            continue
        w = float(st["bin_width_m"])
        edges = np.arange(len(counts) + 1) * w
        a1.stairs(
            counts / counts.sum() / w,
            edges,
            label=f"{suite}: {st['mean_m']:.0f} ± {st['std_m']:.0f} m",
        )
    a1.set(xlabel="pairwise landmark-centroid distance [m]", ylabel="density")
    a1.legend(fontsize=8)
    for k, suite in enumerate(sorted({r["suite"] for r in rho_rows})):
        rr = [r for r in rho_rows if r["suite"] == suite]
        rho, c = [r["rho"] for r in rr], f"C{k % 10}"
        a2.plot(rho, [r["auc"] for r in rr], "o-", color=c, label=f"{suite} AUC")
        a2.plot(rho, [r["recall"] for r in rr], "x--", color=c, label=f"{suite} recall")
    a2.set_xscale("log")
    a2.set(xlabel=r"$\rho$", ylabel="AUC / recall", ylim=(-0.02, 1.02))
    a2.set_title(r"GraffMatch sensitivity to $\rho$")
    a2.grid(alpha=0.3)
    if rho_rows:
        a2.legend(fontsize=8)
    fig.subplots_adjust(left=0.07, right=0.99, bottom=0.13, top=0.92, wspace=0.2)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---- validity ---------------------------------------------------------------------------------
def fig_precision_recall(
    records: Sequence[Mapping[str, Any]], methods: Sequence[str], path: Path, title: str
) -> None:
    """Precision-recall of each method's own validity score (positives and negatives)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4.8))
    groups = group_by(records, "method")
    for m in methods:
        g = groups.get((m,))
        if not g:
            continue
        stats = V.validity_stats(g)
        curve = V.pr_curve(
            [V.score_of(r) for r in g], [V.is_correct(r) for r in g], stats["n_positives"]
        )
        if len(curve["recall"]):
            ax.step(
                np.r_[0.0, curve["recall"]],
                np.r_[1.0, curve["precision"]],
                where="post",
                label=f"{m} ({stats['signal']}; R@P100 {stats['recall_at_full_precision']:.2f})",
            )
    ax.set(xlabel="recall (correct / positives)", ylabel="precision", ylim=(-0.02, 1.02))
    ax.set_xlim(-0.02, 1.02)
    ax.set_title(f"{title}: precision-recall over each method's validity score", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fig_reliability(records: Sequence[Mapping[str, Any]], path: Path, title: str) -> None:
    """Reliability diagram of a confidence meant as a probability: fraction correct per bin."""
    plt = _plt()
    rel = V.reliability([V.score_of(r) for r in records], [V.is_correct(r) for r in records])
    fig, (a1, a2) = plt.subplots(
        2, 1, figsize=(5, 5.5), sharex=True, gridspec_kw={"height_ratios": [3, 1]}
    )
    centres = 0.5 * (rel["bin_edges"][1:] + rel["bin_edges"][:-1])
    filled = rel["counts"] > 0
    a1.plot([0, 1], [0, 1], color="gray", lw=0.8, ls="--", label="calibrated")
    a1.plot(centres[filled], rel["fraction_correct"][filled], "o-", label="fraction correct")
    a1.set(ylabel="fraction correct", ylim=(-0.02, 1.02))
    a1.set_title(f"{title} (ECE {rel['ece']:.3f}, {len(records)} pairs)", fontsize=9)
    a1.legend(fontsize=8)
    a1.grid(alpha=0.3)
    a2.bar(centres, rel["counts"], width=0.09)
    a2.set(xlabel="confidence", ylabel="pairs")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---- the loop-closure dataset ---------------------------------------------------------------
CASE_COLORS = {1: "#2ca02c", 2: "#ff7f0e", 3: "#d62728"}


def plot_dataset_details(ds: LoopClosureDataset, path: str | Path) -> Path:
    """The paper's dataset-details figure: IIR vs sensor distance (coloured by case), and the
    true line and plane matches per case."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 4))
    for c in (1, 2, 3):
        ps = ds.of_case(c)
        ax0.scatter(
            [p.distance for p in ps],
            [p.iir for p in ps],
            s=10,
            alpha=0.7,
            color=CASE_COLORS[c],
            label=f"case {c} ({len(ps)})",
        )
    ax0.set_xlabel("sensor distance [m]")
    ax0.set_ylabel("input inlier ratio")
    ax0.set_yscale("log")
    for y in ds.config.case_thresholds:
        ax0.axhline(y, color="grey", lw=0.8, ls="--")
    ax0.legend(loc="upper right", fontsize=8)
    ax0.set_title(f"{ds.name}: {len(ds)} loop closures")
    data, pos, colors = [], [], []
    for k, c in enumerate((1, 2, 3)):
        ps = ds.of_case(c)
        if not ps:  # an empty case gets no box (not a misleading box at zero)
            continue
        data += [[p.n_true_lines for p in ps], [p.n_true_planes for p in ps]]
        pos += [3 * k + 0.6, 3 * k + 1.4]
        colors += ["#1f77b4", "#9467bd"]
    if data:
        bp = ax1.boxplot(data, positions=pos, widths=0.7, patch_artist=True, showfliers=False)
        for patch, col in zip(bp["boxes"], colors, strict=True):
            patch.set_facecolor(col)
            patch.set_alpha(0.6)
    counts = ds.case_counts()
    ax1.set_xticks([1, 4, 7], [f"case {c}\n(n={counts[c]})" for c in (1, 2, 3)])
    ax1.set_xlim(-0.5, 8.5)
    ax1.set_ylabel("true matches per pair")
    from matplotlib.patches import Patch

    ax1.legend(
        [Patch(color="#1f77b4", alpha=0.6), Patch(color="#9467bd", alpha=0.6)],
        ["lines", "planes"],
        fontsize=8,
    )
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
