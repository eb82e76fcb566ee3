"""Figures for docs/figures/: the uncertainty timeline and the denoising vector field."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from lab.fields import FieldEpisode, context_for  # noqa: E402
from policy.uncertainty import UncertaintyResult  # noqa: E402

MODE_COLOURS = ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown"]


def plot_timeline(ep: FieldEpisode, threshold: float | None, out: Path, title: str) -> Path:
    u = np.asarray(ep.uncertainty)
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(8, 5), sharex=True, height_ratios=[2, 1])
    ax.plot(u, color="black", lw=1.2, label="U = D + α·Var_g")
    if threshold is not None:
        ax.axhline(threshold, color="tab:red", ls="--", lw=1, label=f"threshold (val. 95%) = {threshold:.3f}")
        ax.fill_between(
            np.arange(len(u)),
            0,
            u.max() * 1.05,
            where=u >= threshold,
            color="tab:red",
            alpha=0.12,
            label="would ask for help",
        )
    peak = int(u.argmax())
    ax.axvline(peak, color="tab:blue", lw=0.8)
    ax.set_ylabel("uncertainty U")
    ax.set_title(f"{title}: {'success' if ep.success else 'failure'} in {ep.steps} steps; peak at step {peak}")
    ax.legend(loc="upper left", fontsize=8)
    label, _ = context_for(ep.task)
    ax2.plot(ep.context, color="tab:green")
    ax2.axvline(peak, color="tab:blue", lw=0.8)
    ax2.set_ylabel(label, fontsize=8)
    ax2.set_xlabel("control step (20 Hz)")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def _principal_plane(v: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal basis of the two leading principal directions of the vectors."""
    centred = v - v.mean(0)
    _, _, vt = np.linalg.svd(np.vstack([centred, v]), full_matrices=False)
    return vt[:2].T


def plot_field(r: UncertaintyResult, out: Path, title: str) -> Path:
    """Left: the samples with their denoising vectors; right: the vectors themselves with the mode means.

    Both are projected onto the plane of the vectors' two leading principal directions.
    """
    basis = _principal_plane(r.vectors)
    pos = (r.samples - r.samples.mean(0)) @ basis
    vec = r.vectors @ basis
    colours = [MODE_COLOURS[i % len(MODE_COLOURS)] for i in r.labels]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4.6))
    scale = np.abs(pos).max() / max(np.linalg.norm(vec, axis=1).max(), 1e-9) * 0.6
    a.quiver(
        pos[:, 0],
        pos[:, 1],
        vec[:, 0] * scale,
        vec[:, 1] * scale,
        color=colours,
        angles="xy",
        scale_units="xy",
        scale=1,
        width=0.004,
    )
    a.set_title("denoising vectors at the probe samples")
    a.set_xlabel("principal direction 1 (normalized action)")
    a.set_ylabel("principal direction 2")
    a.set_aspect("equal")
    b.scatter(vec[:, 0], vec[:, 1], c=colours, s=12)
    means = r.means @ basis
    for i, (m, w) in enumerate(zip(means, r.weights, strict=True)):
        b.scatter(
            *m,
            marker="X",
            s=160,
            color=MODE_COLOURS[i % len(MODE_COLOURS)],
            edgecolor="black",
            label=f"mode {i}: weight {w:.2f}",
        )
    b.axhline(0, color="grey", lw=0.5)
    b.axvline(0, color="grey", lw=0.5)
    b.set_title(f"vectors by mode: n = {r.n}, D = {r.D:.3f}, Var_g = {r.var_g:.3f}")
    b.set_xlabel("ε component along direction 1")
    b.set_ylabel("ε component along direction 2")
    b.legend(fontsize=8)
    fig.suptitle(f"{title}: U = {r.U:.3f}")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def plot_signal_comparison(episode, thresholds: dict[str, float], out: Path, title: str) -> Path:
    """Every signal's score over one assisted episode, each divided by its own threshold (1 = asks),
    with the operator's steps shaded: the signals compared on the same trajectory."""
    names = [n for n in episode.scores if n not in ("full-teleop", "random")]
    fig, axes = plt.subplots(len(names), 1, figsize=(8, 1.3 * len(names) + 1), sharex=True, squeeze=False)
    operator = np.asarray(episode.operator, dtype=bool)
    steps = np.arange(len(operator))
    for ax, name in zip(axes[:, 0], names, strict=True):
        ratio = np.asarray(episode.scores[name], dtype=float) / max(thresholds[name], 1e-12)
        top = max(2.0, float(np.nanmax(ratio)) * 1.05) if np.isfinite(ratio).any() else 2.0
        ax.fill_between(steps, 0, top, where=operator, color="tab:orange", alpha=0.2, step="mid", lw=0)
        ax.plot(steps, ratio, color="black", lw=1)
        ax.axhline(1.0, color="tab:red", ls="--", lw=0.8)
        ax.set_ylim(0, top)
        ax.set_ylabel(name, rotation=0, ha="right", va="center", fontsize=8)
    axes[0, 0].set_title(
        f"{title}\nscore / threshold (red: asks); shaded: operator in control ({episode.driver} drives)", fontsize=9
    )
    axes[-1, 0].set_xlabel("control step")
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
