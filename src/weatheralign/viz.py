"""Figures people look at: camera mosaics and LiDAR bird's-eye views with boxes."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from numpy.typing import NDArray  # noqa: E402
from PIL import Image  # noqa: E402

from weatheralign.data.frame import Frame  # noqa: E402
from weatheralign.geometry import apply, invert  # noqa: E402

MOSAIC_ORDER = (("CAM_FRONT_LEFT", "CAM_FRONT", "CAM_FRONT_RIGHT"), ("CAM_BACK_LEFT", "CAM_BACK", "CAM_BACK_RIGHT"))
CLASS_COLOURS = {"vehicle.car": "tab:orange", "vehicle.truck": "tab:brown", "vehicle.bus.rigid": "tab:red",
                 "vehicle.bicycle": "tab:pink", "vehicle.motorcycle": "tab:purple",
                 "human.pedestrian.adult": "tab:blue", "movable_object.barrier": "tab:gray",
                 "movable_object.trafficcone": "gold"}


def camera_mosaic(frame: Frame, width: int = 1800) -> NDArray[np.uint8]:
    """The six images in the nuScenes layout (front row, back row) as one uint8 image ``width`` pixels wide."""
    tile_w = width // 3
    rows = []
    for row in MOSAIC_ORDER:
        tiles = []
        for ch in row:
            view = frame.cameras[ch]
            tile_h = int(round(tile_w * view.height / view.width))
            tiles.append(np.asarray(Image.fromarray(view.load_image()).resize((tile_w, tile_h), Image.BILINEAR)))
        rows.append(np.concatenate(tiles, axis=1))
    return np.concatenate(rows, axis=0)


def ego_forward_in_lidar(T_ego_lidar: NDArray) -> NDArray:
    """(2,) unit direction in the LiDAR's x-y plane of the ego's forward axis (ego x) for the LiDAR -> ego transform
    ``T_ego_lidar`` (4, 4): (1, 0) for an x-forward mount, (0, 1) for nuScenes' LIDAR_TOP (x right, y forward)."""
    direction = np.asarray(T_ego_lidar, dtype=np.float64)[:3, :3].T @ np.array([1.0, 0.0, 0.0])
    return direction[:2] / max(float(np.linalg.norm(direction[:2])), 1e-12)


def bev_figure(frame: Frame, extent_m: float = 60.0, title: str = "",
               point_colour: NDArray | None = None, cmap: str = "viridis") -> Figure:
    """Bird's-eye view of the scan in the LiDAR frame (coloured by intensity unless ``point_colour`` (N,) is given)
    with the annotation boxes outlined by class and an arrow along the ego's forward axis (the axes are the LiDAR's:
    a real nuScenes LIDAR_TOP has x to the right and y forward)."""
    scan = frame.lidar
    p = scan.points
    colour = np.log1p(scan.intensity_255()) if point_colour is None else point_colour
    fig, ax = plt.subplots(figsize=(7, 7))
    ax.scatter(p[:, 0], p[:, 1], s=1.2, c=colour, cmap=cmap, linewidths=0)
    T = invert(scan.T_global_lidar)
    for box in frame.boxes:
        c, s = np.cos(box.yaw), np.sin(box.yaw)
        w, length = box.size[0], box.size[1]
        corners = np.array([[length / 2, w / 2], [length / 2, -w / 2], [-length / 2, -w / 2], [-length / 2, w / 2],
                            [length / 2, w / 2]])
        xy = corners @ np.array([[c, s], [-s, c]]) + box.center[:2]
        local = apply(T, np.column_stack([xy, np.full(len(xy), box.center[2])]))
        ax.plot(local[:, 0], local[:, 1], color=CLASS_COLOURS.get(box.category, "k"), lw=1.2)
    for name, col in CLASS_COLOURS.items():
        ax.plot([], [], color=col, label=name.split(".", 1)[-1])
    ax.set_xlim(-extent_m, extent_m)
    ax.set_ylim(-extent_m, extent_m)
    ax.set_aspect("equal")
    forward = ego_forward_in_lidar(scan.T_ego_lidar)
    ax.annotate("", xy=tuple(0.25 * extent_m * forward), xytext=(0.0, 0.0),
                arrowprops={"arrowstyle": "->", "color": "red", "lw": 2.0})
    ax.plot([], [], color="red", lw=2.0, label="ego forward")
    ax.legend(loc="upper right", fontsize=7)
    ax.set_xlabel("x of LIDAR_TOP [m]")
    ax.set_ylabel("y of LIDAR_TOP [m]")
    ax.set_title(title or f"LIDAR_TOP, {len(p):,} points")
    fig.tight_layout()
    return fig


def size_histogram_figure(diameters: dict[str, NDArray], pdfs: dict[str, tuple[NDArray, NDArray]]) -> Figure:
    """Realised diameter histograms (density per mm) against the size distributions' pdfs, one panel per
    condition. ``diameters``: condition -> (N,) [m]; ``pdfs``: condition -> (D grid [m], pdf [1/m])."""
    fig, axes = plt.subplots(1, len(diameters), figsize=(5.5 * len(diameters), 4), squeeze=False)
    for ax, (name, d) in zip(axes[0], diameters.items()):
        grid, pdf = pdfs[name]
        bins = np.linspace(float(grid[0]), float(grid[-1]), 40)
        ax.hist(d * 1e3, bins=bins * 1e3, density=True, alpha=0.55, label=f"materialised ({len(d):,})")
        ax.plot(grid * 1e3, pdf * 1e-3, "k-", lw=1.5, label="size distribution")
        ax.set_yscale("log")
        ax.set_xlabel("diameter [mm]")
        ax.set_ylabel("probability density [1/mm]")
        ax.set_title(name)
        ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def particle_side_view(xz: NDArray, diameters: NDArray, lidar_origin: tuple[float, float],
                       elevations_deg: NDArray, camera_origin: tuple[float, float], camera_half_vfov_deg: float,
                       extent: tuple[float, float, float, float], title: str) -> Figure:
    """Side view (ego x forward vs z up) of particles ``xz`` (N, 2) [m] sized by ``diameters`` (N,) [m], with the
    LiDAR's ring beams and the front camera's vertical field of view drawn from their mounting points."""
    fig, ax = plt.subplots(figsize=(11, 4))
    x0, x1, z0, z1 = extent
    ax.scatter(xz[:, 0], xz[:, 1], s=np.clip(diameters * 1e3, 0.3, 12), c="tab:blue", alpha=0.6,
               linewidths=0, label=f"particles ({len(xz):,})")
    for k, e in enumerate(np.deg2rad(elevations_deg)):
        r = x1 - lidar_origin[0]
        end = (lidar_origin[0] + r * np.cos(e), lidar_origin[1] + r * np.sin(e))
        ax.plot([lidar_origin[0], end[0]], [lidar_origin[1], end[1]], color="tab:red", lw=0.4, alpha=0.7,
                label="LiDAR rings" if k == 0 else None)
    for k, sign in enumerate((1, -1)):
        a = np.deg2rad(sign * camera_half_vfov_deg)
        r = x1 - camera_origin[0]
        ax.plot([camera_origin[0], camera_origin[0] + r], [camera_origin[1], camera_origin[1] + r * np.tan(a)],
                color="tab:green", lw=1.5, label="CAM_FRONT field of view" if k == 0 else None)
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_xlim(x0, x1)
    ax.set_ylim(z0, z1)
    ax.set_aspect("equal")
    ax.set_xlabel("x forward [m]")
    ax.set_ylabel("z up [m]")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return fig
