"""Matplotlib frames of the environments and animations of episodes.

Kept apart from the physics: the env modules hand plain numpy arrays to the drawing
functions here. Figures are made with the object-oriented API on an Agg canvas, so
rendering never touches pyplot's global state or needs a display.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from beacon_torch.files import create_file

FRAME_SIZE = (6.4, 4.0)  # inches
FRAME_DPI = 80
ACTION_COLOR = "#d62728"


def new_figure(size: tuple[float, float] = FRAME_SIZE, dpi: int = FRAME_DPI) -> Figure:
    fig = Figure(figsize=size, dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def to_rgb(fig: Figure) -> np.ndarray:
    """The figure as an ``H x W x 3`` uint8 array."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def action_bars(
    ax,
    values: Sequence[float],
    labels: Sequence[str],
    limits: Sequence[tuple[float, float]],
) -> None:
    """Vertical bars of the applied actions, each drawn within its own range.

    A bar grows from zero when its range straddles zero (a signed forcing), else from
    the bottom of its range (a gain).
    """
    n = len(values)
    for i, (v, (lo, hi)) in enumerate(zip(values, limits, strict=True)):
        base = 0.0 if lo < 0.0 < hi else lo
        frac = lambda x, lo=lo, hi=hi: (min(max(x, lo), hi) - lo) / (hi - lo)
        ax.bar(i, 1.0, color="#eeeeee", edgecolor="#999999", width=0.6)
        ax.bar(i, frac(v) - frac(base), bottom=frac(base), color=ACTION_COLOR, width=0.6)
        ax.hlines(frac(base), i - 0.3, i + 0.3, color="#555555", lw=0.8)
        if n <= 4:  # more values than that do not fit above the bars
            # a value decaying towards zero reads as zero, not as its last denormal
            shown = v if abs(v) > 1e-6 * (hi - lo) else 0.0
            ax.text(i, 1.03, f"{shown:+.3g}", ha="center", va="bottom", fontsize=8)
    ax.set_xticks(range(n), labels, fontsize=8)
    ax.set_ylim(0.0, 1.15)
    ax.set_yticks([])
    ax.set_xlim(-0.6, n - 0.4)
    ax.set_title("action", fontsize=9)


def lorenz_frame(xyz: np.ndarray, u: float, t: float) -> np.ndarray:
    """The attractor trajectory so far (``xyz``: ``[T, 3]``) with the forcing bar."""
    fig = new_figure()
    # inset from the figure's edges, so that the lowest ticks and labels show whole
    ax = fig.add_axes((0.03, 0.05, 0.76, 0.85), projection="3d")
    x, y, z = xyz.T
    ax.plot(x, y, z, lw=0.7, color="#1f77b4")
    color = "#2ca02c" if x[-1] < 0 else "#7f7f7f"
    ax.scatter([x[-1]], [y[-1]], [z[-1]], color=color, s=30, depthshade=False)
    ax.set_xlim(-25, 25)
    ax.set_ylim(-30, 30)
    ax.set_zlim(0, 50)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    fig.suptitle(f"lorenz   t = {t:.2f}   x {'<' if x[-1] < 0 else '>='} 0", fontsize=10)
    bars = fig.add_axes((0.84, 0.12, 0.13, 0.7))
    action_bars(bars, [u], ["u"], [(-1.0, 1.0)])
    return to_rgb(fig)


def vortex_frame(ay: np.ndarray, k: float, phi: float, t: float) -> np.ndarray:
    """The orbits of A and Y in their complex planes (``ay``: ``[T, 4]``) and the
    gain and phase bars."""
    fig = new_figure()
    for j, (name, cols) in enumerate((("A", (0, 1)), ("Y", (2, 3)))):
        ax = fig.add_axes((0.1 + 0.37 * j, 0.14, 0.27, 0.66))
        re, im = ay[:, cols[0]], ay[:, cols[1]]
        ax.plot(re, im, lw=0.7, color="#1f77b4")
        ax.scatter([re[-1]], [im[-1]], color=ACTION_COLOR, s=20, zorder=3)
        lim = max(1e-3, 1.1 * float(np.abs(ay[:, list(cols)]).max()))
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        ax.set_xlabel(f"Re {name}", fontsize=8)
        ax.set_ylabel(f"Im {name}", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.ticklabel_format(style="sci", scilimits=(-2, 2))
        ax.locator_params(nbins=4)
        ax.set_title(f"{name}-plane", fontsize=9)
    fig.suptitle(f"vortex   t = {t:.1f}", fontsize=10)
    bars = fig.add_axes((0.83, 0.14, 0.15, 0.65))
    action_bars(bars, [k, phi], ["k", "phi"], [(0.0, 0.3), (-math.pi, math.pi)])
    return to_rgb(fig)


def side_by_side_frames(left: Sequence[np.ndarray], right: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Frames of two episodes side by side, labelled "controlled" and "uncontrolled"
    (the shorter one's last frame held while the other goes on)."""
    from PIL import Image, ImageDraw

    n = max(len(left), len(right))
    out = []
    for k in range(n):
        pair = [frames[min(k, len(frames) - 1)] for frames in (left, right)]
        image = Image.fromarray(np.concatenate(pair, axis=1))
        draw = ImageDraw.Draw(image)
        for j, label in enumerate(("controlled", "uncontrolled")):
            draw.text((j * pair[0].shape[1] + 6, 4), label, fill=(0, 0, 0))
        out.append(np.asarray(image))
    return out


def save_animation(frames: Iterable[np.ndarray], path: str | Path, fps: int = 20) -> Path:
    """Write RGB frames to an animated GIF, a new file."""
    from PIL import Image

    images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames]
    if not images:
        raise ValueError("no frames to write")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    duration = max(1, round(1000 / fps))
    # a new file, refused if the name was taken meanwhile (a link at ``path`` included)
    return create_file(
        path,
        lambda tmp: images[0].save(
            tmp, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0
        ),
    )


def _profile_axes(fig, with_bars_width: float = 0.16):
    ax = fig.add_axes((0.11, 0.14, 0.84 - with_bars_width, 0.74))
    bars = fig.add_axes((0.97 - with_bars_width + 0.04, 0.14, with_bars_width - 0.05, 0.64))
    return ax, bars


def burgers_frame(x: np.ndarray, u: np.ndarray, x_ctrl: float, u_target: float, action: float, t: float) -> np.ndarray:
    """The velocity profile, the target, the actuator position and its bar."""
    fig = new_figure()
    ax, bars = _profile_axes(fig)
    ax.plot(x, u, lw=1.0, color="#1f77b4")
    ax.axhline(u_target, color="#555555", lw=0.6, ls="--")
    ax.axvline(x_ctrl, color=ACTION_COLOR, lw=1.2)
    ax.set_xlim(x[0], x[-1])
    ax.set_ylim(u_target - 0.35, u_target + 0.35)
    ax.set_xlabel("x")
    ax.set_ylabel("u")
    ax.set_title(f"burgers   t = {t:.2f}", fontsize=10)
    action_bars(bars, [action], ["a"], [(-1.0, 1.0)])
    return to_rgb(fig)


def ks_frame(x: np.ndarray, u: np.ndarray, target: np.ndarray, actions: np.ndarray, t: float) -> np.ndarray:
    """The field, the target equilibrium, the actuators' positions and their bars."""
    fig = new_figure()
    ax, bars = _profile_axes(fig, with_bars_width=0.3)
    ax.plot(x, u, lw=1.0, color="#1f77b4")
    ax.plot(x, target, color="#555555", lw=0.6, ls="--")
    for centre in x[:: len(x) // 4]:
        ax.axvline(centre, color=ACTION_COLOR, lw=0.8)
    ax.set_xlim(x[0], x[-1])
    ax.set_ylim(-4.0, 4.0)
    ax.set_xlabel("x")
    ax.set_ylabel("u")
    ax.set_title(f"ks   t = {t:.2f}", fontsize=10)
    action_bars(bars, list(actions), [f"a{i}" for i in range(len(actions))], [(-1.0, 1.0)] * len(actions))
    return to_rgb(fig)


def sloshing_frame(x: np.ndarray, h: np.ndarray, action: float, t: float) -> np.ndarray:
    """The free surface in the tank and the acceleration bar."""
    fig = new_figure()
    ax, bars = _profile_axes(fig)
    ax.fill_between(x, 0.0, h, color="#9ecae1")
    ax.plot(x, h, lw=1.0, color="#08519c")
    ax.axhline(1.0, color="#555555", lw=0.6, ls="--")
    ax.set_xlim(x[0], x[-1])
    ax.set_ylim(0.0, 2.0)
    ax.set_xlabel("x")
    ax.set_ylabel("h")
    ax.set_title(f"sloshing   t = {t:.2f}", fontsize=10)
    action_bars(bars, [action], ["accel."], [(-1.0, 1.0)])
    return to_rgb(fig)


def shkadov_frame(
    x: np.ndarray,
    h_history: np.ndarray,
    jets_x: Sequence[float],
    jet_half_width: float,
    actions: Sequence[float],
    dt_act: float,
    step: int,
    space_time: bool = True,
) -> np.ndarray:
    """The film height with a bar per jet over it, and below it the space-time diagram
    of h over the episode so far (``h_history``: ``[T, n]``, its last row ``step``
    actions into the episode). Without the episode's states (``space_time=False``) the
    panel says how to record them rather than drawing one row as if it were the episode."""
    fig = new_figure(size=(6.4, 5.2))
    ax = fig.add_axes((0.09, 0.56, 0.88, 0.36))
    h = h_history[-1]
    ax.plot(x, h, lw=0.8, color="#1f77b4")
    ax.axhline(1.0, color="#555555", lw=0.5, ls="--")
    top = max(2.0, float(h.max()) * 1.05)
    scale = 0.5 * (top - 1.0)
    for xj, a in zip(jets_x, actions, strict=True):
        ax.axvspan(xj - jet_half_width, xj + jet_half_width, color="#dddddd", lw=0)
        ax.bar(xj, a * scale, bottom=1.0, width=2 * jet_half_width, color=ACTION_COLOR, alpha=0.8)
    ax.set_xlim(x[0], x[-1])
    ax.set_ylim(0.0, top)
    ax.set_ylabel("h")
    ax.set_title(f"shkadov   t = {dt_act * step:.2f}   (red: jet actions)", fontsize=10)
    st = fig.add_axes((0.09, 0.09, 0.88, 0.36))
    if not space_time:
        st.set_axis_off()
        st.text(0.5, 0.5, "space-time diagram: make the env with record_history=True", ha="center", va="center")
        return to_rgb(fig)
    t_end = dt_act * step
    t_start = t_end - dt_act * (len(h_history) - 1)
    st.imshow(
        h_history,
        aspect="auto",
        origin="lower",
        extent=(x[0], x[-1], t_start, max(t_end, t_start + dt_act)),
        cmap="viridis",
        vmin=0.5,
        vmax=max(1.5, float(h_history.max())),
        interpolation="nearest",
    )
    for xj in jets_x:
        st.axvline(xj, color="white", lw=0.5, alpha=0.6)
    st.set_xlabel("x")
    st.set_ylabel("t")
    return to_rgb(fig)


def cavity_frame(
    name: str,
    scalar: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    L: float,
    H: float,
    actions: Sequence[float],
    t: float,
    scalar_label: str,
    vmin: float,
    vmax: float,
    action_labels: Sequence[str] | None = None,
) -> np.ndarray:
    """A 2-D cavity: the scalar field (``[nx, ny]``, x first) with velocity arrows at the
    cell centres (from the ghosted staggered ``u``, ``v``) and the action bars."""
    fig = new_figure(size=(6.4, 4.6))
    ax = fig.add_axes((0.06, 0.1, 0.62, 0.8))
    nx, ny = scalar.shape
    image = ax.imshow(
        scalar.T, origin="lower", extent=(0, L, 0, H), cmap="RdBu_r", vmin=vmin, vmax=vmax, interpolation="bilinear"
    )
    uc = 0.5 * (u[1:-2, 1:-1] + u[2:-1, 1:-1])
    vc = 0.5 * (v[1:-1, 1:-2] + v[1:-1, 2:-1])
    step = max(1, nx // 12)
    xs = (np.arange(nx) + 0.5) * L / nx
    ys = (np.arange(ny) + 0.5) * H / ny
    X, Y = np.meshgrid(xs[::step], ys[::step], indexing="ij")
    if np.abs(uc).max() + np.abs(vc).max() > 0:  # quiver cannot scale an all-zero field
        ax.quiver(X, Y, uc[::step, ::step], vc[::step, ::step], color="k", alpha=0.7, width=0.004)
    ax.set_xlim(0, L)
    ax.set_ylim(0, H)
    ax.set_title(f"{name}   t = {t:.1f}", fontsize=10)
    fig.colorbar(image, ax=ax, fraction=0.046, pad=0.02, label=scalar_label)
    bars = fig.add_axes((0.8, 0.14, 0.18, 0.64))
    labels = action_labels or [str(i) for i in range(len(actions))]
    action_bars(bars, list(actions), labels, [(-1.0, 1.0)] * len(actions))
    return to_rgb(fig)
