"""The chart of studies/speed_accuracy.py: one PNG per model, one panel per error measure, x = error (log), y =
throughput (log); torchsim series per method and dtype over substeps, MuJoCo C series per integrator over timesteps."""

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt
import numpy as np

METHOD_COLOURS = {"spring": "tab:blue", "xpbd": "tab:orange", "spring_soft": "tab:purple", "Euler": "black",
                  "implicitfast": "tab:gray", "RK4": "tab:brown"}
DTYPE_MARKERS = {"float32": "o", "float64": "s"}
LABELS = {"joint_rms_rad": "joint-angle RMS error [rad]", "joint_max_rad": "max joint-angle error [rad]",
          "settle_err_m": "settled root height error [m]", "root_err_m": "max root position error, 0.25 s [m]"}
FLOOR = 1e-12  # errors of exactly 0 sit here on the log axis


def _series(rows: list[dict]) -> dict:
    """Rows grouped by (engine, method, dtype), each group in substep order."""
    groups = {}
    for r in rows:
        groups.setdefault((r["engine"], r["method"], r["dtype"]), []).append(r)
    return {k: sorted(v, key=lambda r: r["substeps"]) for k, v in groups.items()}


def _panel(ax, rows: list[dict], metric: str, ylabel: str) -> None:
    for (engine, method, dtype), group in _series(rows).items():
        x = np.array([max(r[metric], FLOOR) for r in group])
        y = np.array([r["env_steps_per_s"] for r in group])
        bad = np.array([bool(r.get("diverged")) for r in group])
        marker = "^" if engine == "mujoco" else DTYPE_MARKERS[dtype]
        label = f"MuJoCo {method}" if engine == "mujoco" else f"torchsim {method} {dtype}"
        ax.plot(x[~bad], y[~bad], marker=marker, color=METHOD_COLOURS[method], label=label, lw=1, ms=6,
                ls="--" if engine == "mujoco" else "-")
        ax.plot(x[bad], y[bad], "x", color="red", ms=9, mew=2)
        for r, xi, yi in zip(group, x, y):
            tag = f"dt/{r['substeps']}" if engine == "mujoco" else str(r["substeps"])
            ax.annotate(tag, (xi, yi), textcoords="offset points", xytext=(4, 3), fontsize=7,
                        color=METHOD_COLOURS[method])
            if r["default"]:
                ax.plot(xi, yi, marker="*", ms=20, mfc="none", mec="green" if engine == "torchsim" else "black",
                        mew=1.5)
    front = sorted((r for r in rows if r.get(f"pareto_{metric}")), key=lambda r: r[metric])
    ax.step([max(r[metric], FLOOR) for r in front], [r["env_steps_per_s"] for r in front], where="post",
            color="green", alpha=0.35, lw=6, label="Pareto front", zorder=0)
    ax.set(xscale="log", yscale="log", xlabel=LABELS[metric], ylabel=ylabel)
    ax.grid(True, which="both", alpha=0.3)


def plot_model(name: str, rows: list[dict], metrics: tuple[str, ...], frame_skip: int, batch: int, threads: int,
               path) -> None:
    """Write the model's chart to ``path``. Numbers next to torchsim points are substeps per model timestep; stars
    mark the env's default (green: torchsim, black: MuJoCo's own timestep and integrator); red crosses: diverged."""
    unit = f"env-steps/s ({frame_skip} timesteps each)" if frame_skip > 1 else "steps/s"
    ylabel = f"{unit}, batch {batch}, {threads} thread{'s' if threads > 1 else ''}"
    fig, axes = plt.subplots(1, len(metrics), figsize=(6.5 * len(metrics), 5), squeeze=False)
    for ax, metric in zip(axes[0], metrics):
        _panel(ax, rows, metric, ylabel)
    axes[0, 0].legend(fontsize=7, loc="best")
    fig.suptitle(f"{name}: speed vs error against MuJoCo at timestep/10 (numbers: substeps; star: default)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
