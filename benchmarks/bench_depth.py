"""Real-data camera depth benchmark: the LiDAR-completed ray lengths against the synthetic world's exact range maps.

Run from the repository root after the world stage (``dvc repro world``):
``.venv/bin/python -m benchmarks.bench_depth [--world DATAROOT] [--samples 12] [--alpha 0.05]``.

On real nuScenes data the cameras have no exact depth: `weatheralign.camera.depth.camera_range_map` completes it
from the LiDAR (the keyframe and earlier sweeps, `weatheralign.simulate.plan.DEPTH_SWEEPS` in all). Every camera of
``--samples`` keyframes spread over the world's scenes is treated as if it had no exact map (``range_path=None``) and
completed from the world's LiDAR alone, once from the keyframe sweep and once with the sweeps (``load_lidar(...,
DEPTH_SWEEPS)``, as `weatheralign.simulate.plan.sample_range_maps` loads them), with the sky the six cameras agree
on (`consistent_sky`) and nearer where the ego's own body (the world manifest's rig) meets the ray, as that function
does on real data, then compared with its exact range map:

- depth: AbsRel, RMSE [m], delta < 1.25 on pixels finite in both; the same within ``--edge-px`` of exact depth edges
  (neighbouring pixels whose ray lengths differ by more than a factor 1.25, sky included);
- sky: precision / recall of the estimated sky (inf) against the exact sky; exact sky given a finite depth, exact
  structure given inf (fractions of the exact sky / structure), and the same for structure nearer than
  ``3 / alpha`` (transmission above 5 %: a facade there taken for sky shows as a white patch in fog);
- halo: each image fogged (``--alpha`` [1/m], one airlight per sample from the exact maps) through the simulator's
  path (`composite_image`: guided-filtered transmission for estimated depth, plain for exact depth); pixels where
  the two differ by more than ``--halo-codes`` sRGB codes (any channel) and connect to an exact transmission edge
  (|dt| > 0.1 between neighbours) form its halo; an edge pixel's halo width is the farthest such pixel [px] whose
  nearest edge pixel it is. Median and 90th percentile over all edge pixels, and the fraction of edge pixels with
  a halo; for the diagnosis also the estimated depth composited without the guided filter, and the exact depth
  with it (the filter's own halo);
- seams: for the six neighbouring camera pairs of the rig, every 4th pixel of one camera is taken as a direction,
  rotated into its neighbour and, where it lands in the image, the two cameras' sky decisions and transmissions
  (``exp(-alpha l)``) are compared: disagreement rate of sky, mean |dt| and fraction |dt| > 0.05, for the estimated
  and for the exact maps (the exact maps' disagreement is parallax and exposure-time difference, the floor);
- time: CPU and wall seconds per camera of the completion.

Real frames (``--real``, default ``/work/shared/data/real`` or ``<repo>/../shared/data/real``): the Seeing Through Fog
and KITTI frames have no exact depth; 10 % of the LiDAR points are held out, depth is completed from the rest and
compared at the held-out points (their ray length from the camera; a held-out point behind a foreground surface seen
by the camera counts as an error, so this is an upper bound). Clean | estimated depth | dense fog previews of both
are written to ``reports/benchmarks/depth_real.png``; a synthetic CAM_FRONT panel (clean, exact and estimated depth,
fog with each, their difference) to ``reports/benchmarks/depth.png``. Results go to ``reports/benchmarks/depth.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from benchmarks.common import REAL, real_frames
from weatheralign.atomic import write_json

REPO = Path(__file__).resolve().parents[1]
REPORT = REPO / "reports" / "benchmarks" / "depth.json"
FIGURE = REPO / "reports" / "benchmarks" / "depth.png"
FIGURE_REAL = REPO / "reports" / "benchmarks" / "depth_real.png"
WORLD_ROOT = REPO / "data" / "world"
EDGE_RATIO = 1.25
T_EDGE = 0.1
SEAM_DT = 0.05
SEAM_STRIDE = 4
PAIRS = (("CAM_FRONT", "CAM_FRONT_RIGHT"), ("CAM_FRONT_RIGHT", "CAM_BACK_RIGHT"), ("CAM_BACK_RIGHT", "CAM_BACK"),
         ("CAM_BACK", "CAM_BACK_LEFT"), ("CAM_BACK_LEFT", "CAM_FRONT_LEFT"), ("CAM_FRONT_LEFT", "CAM_FRONT"))

F32 = NDArray[np.float32]
BoolA = NDArray[np.bool_]


# ------------------------------------------------------------------------------------------------ metrics


def depth_edges(rng: F32, ratio: float = EDGE_RATIO) -> BoolA:
    """(H, W) bool: pixels whose right or lower neighbour's ray length differs by more than ``ratio`` (inf = sky
    differs from everything finite); both pixels of a jump are marked."""
    lr = np.log(np.where(np.isfinite(rng), np.maximum(rng, 1e-3), 1e6)).astype(np.float32)
    thr = math.log(ratio)
    e = np.zeros(rng.shape, bool)
    dh = np.abs(np.diff(lr, axis=1)) > thr
    dv = np.abs(np.diff(lr, axis=0)) > thr
    e[:, :-1] |= dh
    e[:, 1:] |= dh
    e[:-1] |= dv
    e[1:] |= dv
    return e


def near(mask: BoolA, px: int) -> BoolA:
    """(H, W) bool: within ``px`` pixels (L2) of ``mask``."""
    if not mask.any():
        return np.zeros_like(mask)
    return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 3) <= px


@dataclasses.dataclass
class DepthSums:
    """Pooled sums of the depth error on pixels finite in both maps: n, sum |e - g| / g, sum (e - g)^2, n(delta)."""

    n: int = 0
    abs_rel: float = 0.0
    sq: float = 0.0
    delta: int = 0

    def add(self, est: F32, exact: F32, mask: BoolA) -> None:
        m = mask & np.isfinite(est) & np.isfinite(exact) & (exact > 0)
        e, g = est[m].astype(np.float64), exact[m].astype(np.float64)
        self.n += int(m.sum())
        self.abs_rel += float(np.sum(np.abs(e - g) / g))
        self.sq += float(np.sum((e - g) ** 2))
        self.delta += int(np.sum(np.maximum(e / g, g / np.maximum(e, 1e-6)) < 1.25))

    def result(self) -> dict[str, float]:
        n = max(self.n, 1)
        return {"pixels": self.n, "abs_rel": self.abs_rel / n, "rmse_m": math.sqrt(self.sq / n),
                "delta_1.25": self.delta / n}


@dataclasses.dataclass
class SkySums:
    """Pooled counts of estimated vs exact sky: true positives, estimated sky, exact sky, exact structure, exact
    structure nearer than ``near_m`` (where fog still shows it: the sky error that matters) and those taken for sky."""

    tp: int = 0
    est: int = 0
    exact: int = 0
    structure: int = 0
    near: int = 0
    near_sky: int = 0

    def add(self, est: F32, exact: F32, near_m: float) -> None:
        es, gs = np.isposinf(est), np.isposinf(exact)
        close = exact < near_m
        self.tp += int((es & gs).sum())
        self.est += int(es.sum())
        self.exact += int(gs.sum())
        self.structure += int((~gs).sum())
        self.near += int(close.sum())
        self.near_sky += int((es & close).sum())

    def result(self) -> dict[str, float]:
        fp = self.est - self.tp
        return {"precision": self.tp / max(self.est, 1), "recall": self.tp / max(self.exact, 1),
                "exact_sky_given_finite": (self.exact - self.tp) / max(self.exact, 1),
                "exact_structure_given_sky": fp / max(self.structure, 1),
                "exact_structure_near_given_sky": self.near_sky / max(self.near, 1),
                "exact_sky_pixels": self.exact}


def halo_widths(fog_est: NDArray[np.uint8], fog_exact: NDArray[np.uint8], t_exact: F32, codes: int) -> F32:
    """Halo width [px] per exact transmission-edge pixel (|dt| > `T_EDGE` to a neighbour) of one image.

    Pixels whose fogged images differ by more than ``codes`` sRGB codes (any channel) and whose connected region
    (8-neighbourhood) reaches within 2 px of an edge belong to a halo; each is assigned to its nearest edge pixel,
    whose width is the largest distance among its halo pixels (0 without any; both pixels of a jump are edge
    pixels, so a halo on one side leaves the other at 0). Returns (E,) float32 widths."""
    dt_h = np.abs(np.diff(t_exact, axis=1)) > T_EDGE
    dt_v = np.abs(np.diff(t_exact, axis=0)) > T_EDGE
    edge = np.zeros(t_exact.shape, bool)
    edge[:, :-1] |= dt_h
    edge[:, 1:] |= dt_h
    edge[:-1] |= dt_v
    edge[1:] |= dt_v
    if not edge.any():
        return np.zeros(0, np.float32)
    bad = np.abs(fog_est.astype(np.int16) - fog_exact.astype(np.int16)).max(axis=2) > codes
    dist, labels = cv2.distanceTransformWithLabels((~edge).astype(np.uint8), cv2.DIST_L2, 5,
                                                   labelType=cv2.DIST_LABEL_PIXEL)
    n, comp = cv2.connectedComponents(bad.astype(np.uint8), connectivity=8)
    touching = np.unique(comp[bad & (dist <= 2.0)])
    halo = bad & np.isin(comp, touching[touching > 0])
    widths = np.zeros(int(edge.sum()) + 1, np.float32)  # label k = k-th edge pixel in row-major order
    np.maximum.at(widths, labels[halo], dist[halo])
    return widths[1:]


def seam_pairs(view_a: Any, view_b: Any, stride: int = SEAM_STRIDE) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Pixels (va, ua) of ``view_a`` (every ``stride``-th) whose viewing direction in the world falls inside
    ``view_b``, and the pixels (vb, ub) of ``view_b`` that direction lands on (`pixels_in_view`: rotation only)."""
    from weatheralign.camera.depth import pixels_in_view

    vv, uu = np.mgrid[0:view_a.height:stride, 0:view_a.width:stride]
    va, ua = vv.ravel(), uu.ravel()
    ok, vb, ub = pixels_in_view(view_a, view_b, va, ua)
    return va[ok], ua[ok], vb, ub


def seam_stats(r_a: F32, r_b: F32, idx: tuple[NDArray, NDArray, NDArray, NDArray], alpha: float) -> dict[str, float]:
    """Sky disagreement and transmission difference of two range maps at paired pixels (`seam_pairs`)."""
    va, ua, vb, ub = idx
    a, b = r_a[va, ua], r_b[vb, ub]
    ta, tb = np.exp(-alpha * a), np.exp(-alpha * b)
    dt = np.abs(ta - tb)
    n = max(len(a), 1)
    return {"pixels": int(len(a)), "sky_disagree": float(np.sum(np.isposinf(a) != np.isposinf(b)) / n),
            "mean_abs_dt": float(dt.mean()) if len(a) else 0.0, "frac_dt_gt": float(np.sum(dt > SEAM_DT) / n)}


def _pool_seams(rows: list[dict[str, float]]) -> dict[str, float]:
    n = sum(r["pixels"] for r in rows)
    w = max(n, 1)
    return {"pixels": n, "sky_disagree": sum(r["sky_disagree"] * r["pixels"] for r in rows) / w,
            "mean_abs_dt": sum(r["mean_abs_dt"] * r["pixels"] for r in rows) / w,
            "frac_dt_gt": sum(r["frac_dt_gt"] * r["pixels"] for r in rows) / w}


def _halo_summary(widths: list[F32]) -> dict[str, float]:
    w = np.concatenate(widths) if widths else np.zeros(0, np.float32)
    if len(w) == 0:
        return {"edge_pixels": 0}
    pos = w[w > 0]
    return {"edge_pixels": int(len(w)), "median_px": float(np.median(w)), "p90_px": float(np.percentile(w, 90)),
            "p99_px": float(np.percentile(w, 99)), "frac_edges_with_halo": float(len(pos) / len(w)),
            "median_px_where_halo": float(np.median(pos)) if len(pos) else 0.0}


# ------------------------------------------------------------------------------------------------ synthetic


def pick_samples(nusc: Any, count: int) -> list[str]:
    """``count`` keyframe tokens spread over the scenes: round-robin over scenes, each scene's keyframes taken at
    evenly spaced positions."""
    scenes = []
    for scene in nusc.scene:
        toks, tok = [], scene["first_sample_token"]
        while tok:
            toks.append(tok)
            tok = nusc.get("sample", tok)["next"]
        scenes.append(toks)
    per = math.ceil(count / max(len(scenes), 1))
    out: list[str] = []
    for k in range(per):
        for toks in scenes:
            if len(out) < count:
                out.append(toks[min(len(toks) - 1, (2 * k + 1) * len(toks) // (2 * per))])
    return out


def _fog(image: NDArray[np.uint8], rng: F32, alpha: float, a_lin: NDArray, refine: bool) -> NDArray[np.uint8]:
    from weatheralign.camera.fog import composite_image, transmission

    return composite_image(image, transmission(rng, alpha), a_lin, refine)


def _ego_body(world: Path) -> Any:
    """The ego body of the world's sensor rig (its manifest beside the dataroot), None without a manifest."""
    from weatheralign.manifest import manifest_path, read_manifest

    path = manifest_path(world.parent, "world")
    return read_manifest(path).sensors.ego_body if path.is_file() else None


def run_synthetic(world: Path, count: int, alpha: float, edge_px: int, codes: int) -> dict[str, Any]:
    """All the synthetic-world numbers (see the module docstring); keys ``keyframe`` and ``sweeps``."""
    from weatheralign.camera.depth import camera_range_map, consistent_sky
    from weatheralign.camera.fog import estimate_airlight, srgb_to_linear
    from weatheralign.data.nuscenes import load_frame, load_lidar, open_nuscenes
    from weatheralign.simulate.plan import DEPTH_SWEEPS

    nusc = open_nuscenes(world, "v1.0-mini")
    tokens = pick_samples(nusc, count)
    ego = _ego_body(world)
    modes = {"keyframe": 1, "sweeps": DEPTH_SWEEPS}  # load_lidar's count includes the keyframe, as the simulator's
    depth = {m: DepthSums() for m in modes}
    depth_edge = {m: DepthSums() for m in modes}
    sky = {m: SkySums() for m in modes}
    halos: dict[str, list[F32]] = {m: [] for m in (*modes, *(f"{m}_unrefined" for m in modes), "exact_refined")}
    seams: dict[str, list[dict]] = {m: [] for m in (*modes, "exact")}
    cpu: dict[str, list[float]] = {m: [] for m in modes}
    wall: dict[str, list[float]] = {m: [] for m in modes}
    panel: dict[str, Any] = {}
    warm = False
    for si, token in enumerate(tokens):
        frame = load_frame(nusc, token)
        lidar_token = nusc.get("sample", token)["data"]["LIDAR_TOP"]
        scans = {"keyframe": frame.lidar, "sweeps": load_lidar(nusc, lidar_token, modes["sweeps"])}
        views = frame.cameras
        images = {ch: v.load_image() for ch, v in views.items()}
        exact = {ch: v.load_range() for ch, v in views.items()}
        a_lin = srgb_to_linear(estimate_airlight(list(images.values()), list(exact.values())))
        fog_exact = {ch: _fog(images[ch], exact[ch], alpha, a_lin, refine=False) for ch in views}
        for mode, scan in scans.items():
            est: dict[str, F32] = {}
            for ch, view in views.items():
                blind = dataclasses.replace(view, range_path=None)  # as on real data: no exact map
                if not warm:
                    camera_range_map(blind, scan, images[ch])  # JIT / cache load outside the timing
                    warm = True
                c0, w0 = time.process_time(), time.perf_counter()
                est[ch] = camera_range_map(blind, scan, images[ch])
                cpu[mode].append(time.process_time() - c0)
                wall[mode].append(time.perf_counter() - w0)
            # as `sample_range_maps` on real data: the sky the cameras agree on, the ego's body from its geometry
            est = consistent_sky(views, est)
            for ch, view in views.items():
                if ego is not None:
                    est[ch] = np.minimum(est[ch], ego.camera_ranges(view.K, view.T_ego_cam, view.width, view.height))
                g = exact[ch]
                depth[mode].add(est[ch], g, np.ones(g.shape, bool))
                depth_edge[mode].add(est[ch], g, near(depth_edges(g), edge_px))
                sky[mode].add(est[ch], g, 3.0 / alpha)
                fog_est = _fog(images[ch], est[ch], alpha, a_lin, refine=True)
                t_g = np.exp(-alpha * g).astype(np.float32)
                halos[mode].append(halo_widths(fog_est, fog_exact[ch], t_g, codes))
                halos[f"{mode}_unrefined"].append(
                    halo_widths(_fog(images[ch], est[ch], alpha, a_lin, refine=False), fog_exact[ch], t_g, codes))
                if mode == "keyframe":
                    halos["exact_refined"].append(
                        halo_widths(_fog(images[ch], g, alpha, a_lin, refine=True), fog_exact[ch], t_g, codes))
                if si == 0 and ch == "CAM_FRONT" and mode == "sweeps":
                    panel = {"image": images[ch], "exact": g, "est": est[ch], "fog_exact": fog_exact[ch],
                             "fog_est": fog_est}
            for a, b in PAIRS:
                idx = seam_pairs(views[a], views[b])
                seams[mode].append(seam_stats(est[a], est[b], idx, alpha))
                if mode == "keyframe":
                    seams["exact"].append(seam_stats(exact[a], exact[b], idx, alpha))
        print(f"  sample {si + 1}/{len(tokens)} done", flush=True)
    out: dict[str, Any] = {"samples": len(tokens), "cameras": len(tokens) * 6, "sample_tokens": tokens}
    for mode, nsweeps in modes.items():
        out[mode] = {"sweeps_aggregated": nsweeps, "depth_all": depth[mode].result(),
                     f"depth_within_{edge_px}px_of_edges": depth_edge[mode].result(), "sky": sky[mode].result(),
                     "halo": _halo_summary(halos[mode]),
                     "halo_without_guided_filter": _halo_summary(halos[f"{mode}_unrefined"]),
                     "seams": _pool_seams(seams[mode]),
                     "cpu_s_per_camera": float(np.median(cpu[mode])), "wall_s_per_camera": float(np.median(wall[mode])),
                     "cpu_s_total": float(np.sum(cpu[mode]))}
    out["seams_exact"] = _pool_seams(seams["exact"])
    out["halo_exact_depth_guided_filter"] = _halo_summary(halos["exact_refined"])
    out["_panel"] = panel
    return out


# ------------------------------------------------------------------------------------------------ real frames


def holdout_eval(frame: Any, fraction: float = 0.1, seed: int = 0) -> tuple[dict[str, float], F32, float]:
    """Depth completed from (1 - ``fraction``) of the frame's LiDAR points, error at the held-out points (their ray
    length from the camera vs the completed ray length at their pixel). Returns (metrics, full-scan range map (H, W),
    CPU seconds of the full completion)."""
    from weatheralign.camera.depth import camera_points, complete_depth, dense_depth, estimate_top_elevation_deg

    view = next(iter(frame.cameras.values()))
    image = view.load_image()
    top = estimate_top_elevation_deg(frame.lidar)
    pts = camera_points(frame.lidar, view)
    held = np.random.default_rng(seed).random(len(pts.xyz)) < fraction
    kept = dataclasses.replace(pts, xyz=pts.xyz[~held], dt=pts.dt[~held])
    dd = complete_depth(kept, view.K, view.width, view.height, image, top)
    xyz = pts.xyz[held]
    z = xyz[:, 2]
    front = z > 1.0
    xyz, z = xyz[front], z[front]
    u = np.rint(view.K[0, 0] * xyz[:, 0] / z + view.K[0, 1] * xyz[:, 1] / z + view.K[0, 2]).astype(np.int64)
    v = np.rint(view.K[1, 1] * xyz[:, 1] / z + view.K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < view.width) & (v >= 0) & (v < view.height)
    g = np.linalg.norm(xyz[inside], axis=1)
    e = dd.range[v[inside], u[inside]].astype(np.float64)
    fin = np.isfinite(e)
    rel = np.abs(e[fin] - g[fin]) / g[fin]
    metrics = {"held_out_points": int(inside.sum()), "given_sky": float(1.0 - fin.mean()) if len(fin) else 0.0,
               "abs_rel": float(rel.mean()), "median_rel": float(np.median(rel)),
               "p90_rel": float(np.percentile(rel, 90)), "rmse_m": float(np.sqrt(np.mean((e[fin] - g[fin]) ** 2))),
               "delta_1.25": float(np.mean(np.maximum(e[fin] / g[fin], g[fin] / e[fin]) < 1.25))}
    c0 = time.process_time()
    full = dense_depth(frame.lidar, view, image, top).range
    return metrics, full, time.process_time() - c0


def run_real(root: Path, alpha: float) -> tuple[dict[str, Any], list[NDArray[np.uint8]]]:
    """Held-out-point errors and fog previews (rows: clean | estimated depth | dense fog) of the STF and KITTI
    frames that exist under ``root``."""
    from weatheralign.camera.fog import estimate_airlight, srgb_to_linear

    out: dict[str, Any] = {}
    rows = []
    for name, load in real_frames(root).items():
        frame = load()
        metrics, rng, cpu = holdout_eval(frame)
        image = next(iter(frame.cameras.values())).load_image()
        a_lin = srgb_to_linear(estimate_airlight([image], [rng]))
        fog = _fog(image, rng, alpha, a_lin, refine=True)
        out[name] = {**metrics, "sky_fraction": float(np.isposinf(rng).mean()), "cpu_s": cpu,
                     "airlight_linear": [float(x) for x in a_lin]}
        rows.append(np.concatenate([image, colour_depth(rng), fog], axis=1))
    return out, rows


# ------------------------------------------------------------------------------------------------ figures


def colour_depth(rng: F32, far_m: float = 80.0) -> NDArray[np.uint8]:
    """(H, W, 3) uint8 false colour of ray lengths: log scale 1..``far_m`` m (turbo), sky white."""
    x = np.log(np.clip(np.where(np.isfinite(rng), rng, far_m), 1.0, far_m)) / math.log(far_m)
    c = cv2.applyColorMap((255 * (1.0 - x)).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1].copy()
    c[np.isposinf(rng)] = 255
    return c


def save_panel(panel: dict[str, Any], path: Path) -> None:
    """3 x 2 mosaic at half resolution: clean | fog (exact), exact depth | estimated depth, fog (estimated) |
    |difference| x 4."""
    from PIL import Image

    diff = np.clip(4 * np.abs(panel["fog_est"].astype(np.int16) - panel["fog_exact"].astype(np.int16)), 0, 255)
    tiles = [[panel["image"], panel["fog_exact"]], [colour_depth(panel["exact"]), colour_depth(panel["est"])],
             [panel["fog_est"], diff.astype(np.uint8)]]
    mosaic = np.concatenate([np.concatenate(r, axis=1) for r in tiles], axis=0)
    h, w = mosaic.shape[:2]
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(cv2.resize(mosaic, (w // 2, h // 2), interpolation=cv2.INTER_AREA)).save(path)


def save_real(rows: list[NDArray[np.uint8]], path: Path) -> None:
    """Rows (clean | depth | fog) stacked, each scaled to 1800 px wide."""
    from PIL import Image

    scaled = [cv2.resize(r, (1800, int(round(r.shape[0] * 1800 / r.shape[1]))), interpolation=cv2.INTER_AREA)
              for r in rows]
    Image.fromarray(np.concatenate(scaled, axis=0)).save(path)


# ------------------------------------------------------------------------------------------------ main


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", type=Path, default=WORLD_ROOT, help="the synthetic world's dataroot")
    parser.add_argument("--samples", type=int, default=12, help="keyframes (x 6 cameras), spread over the scenes")
    parser.add_argument("--alpha", type=float, default=0.05, help="fog extinction for halo and seams [1/m]")
    parser.add_argument("--edge-px", type=int, default=10, help="band around exact depth edges [px]")
    parser.add_argument("--halo-codes", type=int, default=8, help="sRGB code difference that counts as halo")
    parser.add_argument("--real", type=Path, default=REAL, help="folder of the shared real frames")
    parser.add_argument("--out", type=Path, default=REPORT)
    args = parser.parse_args(argv)
    c0, w0 = time.process_time(), time.perf_counter()
    result: dict[str, Any] = {"alpha_per_m": args.alpha, "halo_codes": args.halo_codes, "edge_px": args.edge_px}
    if (args.world / "v1.0-mini" / "sample_data.json").is_file():
        syn = run_synthetic(args.world, args.samples, args.alpha, args.edge_px, args.halo_codes)
        panel = syn.pop("_panel")
        if panel:
            save_panel(panel, FIGURE)
        result["synthetic"] = {**syn, "world": str(args.world)}
    else:
        print(f"{args.world}: no world dataset (run `dvc repro world`, or pass --world); synthetic part skipped")
    if args.real.is_dir():
        real, rows = run_real(args.real, args.alpha)
        if rows:
            save_real(rows, FIGURE_REAL)
        result["real"] = real
    else:
        print(f"{args.real}: no real frames; real part skipped")
    result["cpu_s"] = time.process_time() - c0
    result["wall_s"] = time.perf_counter() - w0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_json(args.out, result, indent=2)
    print(f"wrote {args.out} ({result['cpu_s']:.0f} CPU-s, {result['wall_s']:.0f} s)")
    return result


if __name__ == "__main__":
    main()
