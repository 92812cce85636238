"""PNG figures in the manner of the paper's Figs. 3-6 (matplotlib, no display needed)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from edge_client.simulation import SimulationResult

TRUE_STYLE = {"color": "tab:blue", "lw": 1.6, "label": "true"}
EST_STYLE = {"color": "tab:red", "lw": 1.2, "ls": "--", "label": "estimated"}
#: The two fault panels: (y label, title).
FAULT_PANELS = (("T_f [N m]", "(a) torque fault"), ("delta_f [rad]", "(b) steering fault"))


def _finish_fault_panel(ax: Any, true: Any, margin: float, ylabel: str, name: str) -> None:
    """Limits around the true fault (0 included) with ``margin`` times its peak on both sides, labels, grid."""
    span = max(float(abs(true).max()), 1e-9)
    ax.set_ylim(min(float(true.min()), 0.0) - margin * span, max(float(true.max()), 0.0) + margin * span)
    ax.set(ylabel=ylabel, title=name)
    ax.grid(alpha=0.3)
    ax.legend(loc="best")


def _save(fig: Any, path: str | Path, title: str) -> Path:
    """Title the figure (when given), write it as PNG and close it."""
    if title:
        fig.suptitle(title)
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_states(result: SimulationResult, path: str | Path, vehicle: int = 0, title: str = "") -> Path:
    """Figs. 3/5: (a) X-Y trajectory, (b) v_x, (c) v_y, (d) r, true vs estimated."""
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5), constrained_layout=True)
    t = result.t
    ax = axes[0, 0]
    ax.plot(result.pose[:, vehicle, 0], result.pose[:, vehicle, 1], color="tab:blue", lw=1.6)
    ax.set(xlabel="X [m]", ylabel="Y [m]", title="(a) trajectory X-Y")
    ax.axis("equal")
    labels = [
        ("v_x [m/s]", "(b) longitudinal speed v_x"),
        ("v_y [m/s]", "(c) lateral speed v_y"),
        ("r [rad/s]", "(d) yaw rate r"),
    ]
    for k, (ylabel, name) in enumerate(labels):
        ax = axes.flat[k + 1]
        ax.plot(t, result.x[:, vehicle, k], **TRUE_STYLE)
        ax.plot(t, result.x_hat[:, vehicle, k], **EST_STYLE)
        ax.set(xlabel="t [s]", ylabel=ylabel, title=name)
        ax.grid(alpha=0.3)
        ax.legend(loc="best")
    return _save(fig, path, title)


def plot_faults(result: SimulationResult, path: str | Path, vehicle: int = 0, title: str = "") -> Path:
    """Figs. 4/6: (a) torque fault T_f, (b) steering fault delta_f, true vs estimated."""
    fig, axes = plt.subplots(2, 1, figsize=(11, 7), constrained_layout=True, sharex=True)
    t = result.t
    for k, (ylabel, name) in enumerate(FAULT_PANELS):
        ax = axes[k]
        ax.plot(t, result.f[:, vehicle, k], **TRUE_STYLE)
        ax.plot(t, result.f_hat[:, vehicle, k], **EST_STYLE)
        _finish_fault_panel(ax, result.f[:, vehicle, k], 0.6, ylabel, name)
    axes[-1].set_xlabel("t [s]")
    return _save(fig, path, title)


def plot_fault_overlay(results: dict[str, SimulationResult], path: str | Path, title: str = "") -> Path:
    """Fault estimates of several estimators on the same run, over the truth."""
    fig, axes = plt.subplots(2, 1, figsize=(11, 7), constrained_layout=True, sharex=True)
    first = next(iter(results.values()))
    styles = [("tab:red", "--"), ("tab:green", ":"), ("tab:purple", "-.")]
    for k, (ylabel, name) in enumerate(FAULT_PANELS):
        ax = axes[k]
        ax.plot(first.t, first.f[:, 0, k], color="tab:blue", lw=1.8, label="true")
        for (label, result), (color, ls) in zip(results.items(), styles, strict=False):
            ax.plot(result.t, result.f_hat[:, 0, k], color=color, ls=ls, lw=1.1, label=label)
        _finish_fault_panel(ax, first.f[:, 0, k], 0.8, ylabel, name)
    axes[-1].set_xlabel("t [s]")
    return _save(fig, path, title)
