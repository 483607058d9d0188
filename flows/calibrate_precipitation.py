"""`calibrate_precipitation` stage: ReDAM for snow and rain — the rates of the simulation tuned to a reference with
real snow and rain.

``python -m flows.calibrate_precipitation`` opens the reference of the `reference` stage (its clear split and the
``snow`` / ``rain`` splits it has) and, per kind: runs the reference's clear scans through the fast particle simulator
(`simulate_particles`, the reference's LiDAR with its detector noise, one mapped task per grid rate of
``calibrate_precipitation.<kind>_rates``), measures the open-path echo rate of every scan
(`weatheralign.calibrate.precipitation`), and finds the rate whose mean matches the reference split's, with a frame
bootstrap interval. The ground likewise (`weatheralign.calibrate.ground`): the clear scans' ground wetted at each film
depth of ``calibrate_precipitation.wet_film_depths_m`` and snowed over at each depth of ``snow_depths_m``, the depth
whose ground statistic (the ground returns' mean intensity; the LiDAR's height above the fitted ground) matches the
rain / snow split's. The two fits meet in the open-path statistic (weak wet returns and snow-lifted ground change
which echoes are isolated and which beams are open), so they go in turn: the ground under the particles params' rate,
the rate grid over the clear scans carrying that ground (`grounded_scans`), the ground again under the tuned rate.
The camera's light: the clear and each weather split's camera frames give the overcast's zenith luminance, the
metering ratio ζ and the diffuse gain over the sun transmittance (`weatheralign.calibrate.overcast.fit_overcast`, one
mapped task per frame; the sun transmittance is not identified and stays the simulation's). The camera side of the
check (KID, visibility) is in the `verify` stage, which simulates the reference frames at these rates.

Writes ``<paths.data>/calibrate_precipitation/rates.json`` (``{snow|rain: {rate_mm_h, ci_low, ci_high}}``,
``{ground: {snow|rain: {depth_m, ci_low, ci_high}}}`` and ``{overcast: {snow|rain: OvercastFit.rates_entry}}``: what
the media stage applies to the particle fields, the ground and the cameras' light with
``simulate.precipitation_rates: calibrated``),
``reports/calibrate_precipitation/details.json`` (its headline in ``metrics.json``) and ``rates.png`` (the
statistic against the rate, per kind, with the reference's mean and interval), also logged to MLflow. The synthetic
reference's sealed truth is never read here.
"""

from __future__ import annotations

import textwrap
import time

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import NullFormatter  # noqa: E402
from prefect import flow  # noqa: E402

from flows.common import gather, parse_stage_args, run_stage  # noqa: E402
from tasks.calibrate import ground_statistics_task, overcast_light_task, precipitation_statistics_task  # noqa: E402
from tasks.tracking import StageTracker  # noqa: E402
from weatheralign import atomic  # noqa: E402
from weatheralign.calibrate.ground import DepthFit, TunedAir, fit_depth, ground_statistic  # noqa: E402
from weatheralign.calibrate.overcast import FrameLight, OvercastFit, fit_overcast  # noqa: E402
from weatheralign.calibrate.precipitation import RateFit, fit_rate, reference_statistics  # noqa: E402
from weatheralign.config import Params  # noqa: E402
from weatheralign.data.errors import DataFormatError  # noqa: E402
from weatheralign.manifest import PRECIPITATION_RATES_FILE  # noqa: E402
from weatheralign.reference import PRECIPITATION_LEVELS, configured_reference, reference_lidar_model  # noqa: E402


def rates_figure(fits: dict[str, RateFit], reference: dict[str, np.ndarray], simulated: dict[str, np.ndarray],
                 ground_depths_m: dict[str, float]):
    """Per kind: the simulated open-path echo rate (mean and per-frame spread; the clear scans carrying the ground of
    ``ground_depths_m``) against the rate, the reference's mean with its frame-bootstrap spread, and the tuned rate
    with its interval."""
    fig, axes = plt.subplots(1, len(fits), figsize=(5.2 * len(fits), 3.8), squeeze=False)
    for ax, (kind, fit) in zip(axes[0], fits.items()):
        rates, sim = np.asarray(fit.rates), simulated[kind]
        ax.fill_between(rates, np.percentile(sim, 10, axis=1), np.percentile(sim, 90, axis=1), color="tab:blue",
                        alpha=0.2, label="simulated, 10-90 % of frames")
        what = "snow" if kind == "snow" else "water film"
        ax.plot(rates, sim.mean(axis=1), "o-", color="tab:blue",
                label=f"simulated mean (ground: {1000 * ground_depths_m[kind]:.3g} mm {what})")
        ref = reference[kind]
        se = ref.std(ddof=1) / np.sqrt(len(ref)) if len(ref) > 1 else 0.0
        ax.axhspan(ref.mean() - 2 * se, ref.mean() + 2 * se, color="0.5", alpha=0.25)
        ax.axhline(ref.mean(), color="black", lw=1.2, label=f"reference {kind} ({len(ref)} frames) ± 2 SE")
        ax.axvline(fit.rate_mm_h, color="tab:red", lw=1.5, label=f"tuned {fit.rate_mm_h:.3g} mm/h")
        ax.axvspan(fit.ci_low, fit.ci_high, color="tab:red", alpha=0.12)
        ax.set(xscale="log", yscale="log", xlabel=f"{kind} rate [mm/h]", ylabel="isolated echoes per open beam",
               title=f"{kind}: open-path echo rate (≤ 20 m)")
        ax.set_xticks(rates, [f"{r:g}" for r in rates])
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def fit_ground(ds, kind: str, rate_mm_h: float, lidar, params: Params) -> tuple[DepthFit, np.ndarray, np.ndarray]:
    """The ground depth of ``kind``'s split: the clear scans' ground at every depth of the grid under the tuned
    ``rate_mm_h`` (one mapped task per depth), the split's own statistic, `fit_depth`. Returns the fit, the
    simulated (D, F) and reference (F,) statistics."""
    cfg = params.calibrate_precipitation
    grid = tuple(cfg.snow_depths_m if kind == "snow" else cfg.wet_film_depths_m)
    particles = params.particles.model_copy(update={kind: getattr(params.particles, kind).model_copy(
        update={"rate_mm_h": rate_mm_h})})
    air = TunedAir(particles, lidar)
    futures = [ground_statistics_task.submit(ds, kind, depth, air) for depth in grid]
    simulated = np.stack(gather(futures, f"calibrate_precipitation {kind}: ground grid", params.run.show_progress))
    reference = np.array([ground_statistic(ds.load_scan(i), kind) for i in ds.ids(kind)])
    fit = fit_depth(reference, simulated, grid, kind, num_bootstrap=cfg.num_bootstrap, confidence=cfg.confidence,
                    seed=cfg.seed)
    return fit, simulated, reference


def frame_lights(ds, ids: list[str], what: str, show_progress: bool) -> list[FrameLight]:
    """The light of each of the reference frames ``ids`` (one mapped task per frame)."""
    return gather([overcast_light_task.submit(ds, i) for i in ids], f"calibrate_precipitation {what}: frame light",
                  show_progress)


def fit_light(clear: list[FrameLight], weather: list[FrameLight], kind: str, params: Params) -> OvercastFit | None:
    """`fit_overcast` of ``kind``'s split (None, with a warning, where its frames show no unsaturated sky)."""
    cfg = params.calibrate_precipitation
    try:
        return fit_overcast(clear, weather, num_bootstrap=cfg.num_bootstrap, confidence=cfg.confidence,
                            seed=cfg.seed)
    except ValueError as exc:
        print(f"calibrate_precipitation {kind} light: WARNING: {exc}; the simulation keeps simulate.overcast_*")
        return None


def ground_figure(fits: dict[str, DepthFit], reference: dict[str, np.ndarray], simulated: dict[str, np.ndarray]):
    """Per kind: the ground statistic of the clear scans edited at each grid depth (mean and 10-90 % of frames),
    the weather split's mean with ± 2 standard errors, and the tuned depth with its interval."""
    fig, axes = plt.subplots(1, len(fits), figsize=(5.2 * len(fits), 3.8), squeeze=False)
    for ax, (kind, fit) in zip(axes[0], fits.items()):
        depths_mm = 1000.0 * np.asarray(fit.depths_m)
        sim = simulated[kind][:, np.all(np.isfinite(simulated[kind]), axis=0)]
        ref = reference[kind][np.isfinite(reference[kind])]
        ax.fill_between(depths_mm, np.percentile(sim, 10, axis=1), np.percentile(sim, 90, axis=1), color="tab:blue",
                        alpha=0.2, label="clear scans edited, 10-90 % of frames")
        ax.plot(depths_mm, sim.mean(axis=1), "o-", color="tab:blue", label="simulated mean")
        se = ref.std(ddof=1) / np.sqrt(len(ref)) if len(ref) > 1 else 0.0
        ax.axhspan(ref.mean() - 2 * se, ref.mean() + 2 * se, color="0.5", alpha=0.25)
        ax.axhline(ref.mean(), color="black", lw=1.2, label=f"reference {kind} ({len(ref)} frames) ± 2 SE")
        ax.axvline(1000 * fit.depth_m, color="tab:red", lw=1.5, label=f"tuned {1000 * fit.depth_m:.3g} mm")
        ax.axvspan(1000 * fit.ci_low, 1000 * fit.ci_high, color="tab:red", alpha=0.12)
        what = "snow depth" if kind == "snow" else "mean water-film depth"
        ax.set(xlabel=f"{what} [mm]", ylabel=textwrap.fill(fit.statistic, 40), title=f"{kind}: the ground")
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


HEADLINE = ("rate_mm_h",)
"""Per kind, the figures of reports/calibrate_precipitation/metrics.json (the rest, intervals and the statistic on
the rate grid included, in details.json and the MLflow child run of each kind)."""


GROUND_HEADLINE = ("depth_m",)
"""Per kind, the ground's figures of metrics.json (as ``ground_<name>``)."""


def headline(details: dict) -> dict:
    """Per calibrated kind its `HEADLINE` and `GROUND_HEADLINE` figures."""
    return {kind: {**{k: details[kind].get(k) for k in HEADLINE},
                   **{f"ground_{k}": details[kind].get("ground", {}).get(k) for k in GROUND_HEADLINE}}
            for kind in details["kinds"]}


@flow(name="calibrate_precipitation", log_prints=True)
def calibrate_precipitation_flow(params: Params) -> dict:
    """The tuned rate per precipitation split of the reference; returns the figures written to
    reports/calibrate_precipitation/details.json."""
    cfg = params.calibrate_precipitation
    t0 = time.time()
    with StageTracker(params, "calibrate_precipitation") as tracker:
        ds = configured_reference(params, ("clear", *PRECIPITATION_LEVELS))
        kinds = [k for k in PRECIPITATION_LEVELS if k in ds.splits and ds.ids(k)]
        lidar = reference_lidar_model(params, ds)
        tracker.log_params({"calibrate_precipitation": cfg.model_dump(mode="json"),
                            "reference.source": params.reference.source, "reference_lidar": lidar.to_dict()})
        clear = ds.ids("clear")
        if len(clear) < 2:
            raise DataFormatError(f"reference {ds.root}: calibrate_precipitation needs a clear split of two frames "
                                  f"or more")
        metrics: dict = {"reference_root": str(ds.root), "reference_source": params.reference.source,
                         "kinds": kinds, "statistic": "isolated returns within 20 m per open beam"}
        rates, fits, reference, simulated = {}, {}, {}, {}
        ground, ground_fits, ground_reference, ground_simulated = {}, {}, {}, {}
        light: dict[str, dict] = {}
        clear_light = frame_lights(ds, clear, "clear", params.run.show_progress) if kinds else []
        for kind in kinds:
            t_kind = time.time()
            configured_rate = getattr(params.particles, kind).rate_mm_h
            first, _, _ = fit_ground(ds, kind, configured_rate, lidar, params)
            print(f"calibrate_precipitation {kind} ground, first pass under the configured {configured_rate:g} mm/h: "
                  f"{1000 * first.depth_m:.3g} mm")
            grid = tuple(cfg.snow_rates if kind == "snow" else cfg.rain_rates)
            futures = [precipitation_statistics_task.submit(ds, kind, rate, lidar, params.particles, first.depth_m)
                       for rate in grid]
            simulated[kind] = np.stack(gather(futures, f"calibrate_precipitation {kind}: rate grid",
                                              params.run.show_progress))
            reference[kind] = reference_statistics([ds.load_scan(i) for i in ds.ids(kind)], lidar)
            fit = fit_rate(reference[kind], simulated[kind], grid, num_bootstrap=cfg.num_bootstrap,
                           confidence=cfg.confidence, seed=cfg.seed)
            fits[kind] = fit
            rates[kind] = {"rate_mm_h": fit.rate_mm_h, "ci_low": fit.ci_low, "ci_high": fit.ci_high}
            metrics[kind] = {**fit.metrics(), "frames_reference": len(reference[kind]), "frames_clear": len(clear),
                             "rate_grid_ground_depth_m": first.depth_m}
            print(f"calibrate_precipitation {kind}: {fit.rate_mm_h:.3g} mm/h [{fit.ci_low:.3g}, {fit.ci_high:.3g}] "
                  f"(reference {fit.reference_mean:.4g} isolated echoes per open beam)"
                  + (f"; WARNING: outside the simulated grid {list(grid)}, widen calibrate_precipitation."
                     f"{kind}_rates" if fit.beyond_grid else ""))
            ground_fits[kind], ground_simulated[kind], ground_reference[kind] = fit_ground(ds, kind, fit.rate_mm_h,
                                                                                           lidar, params)
            g = ground_fits[kind]
            ground[kind] = {"depth_m": g.depth_m, "ci_low": g.ci_low, "ci_high": g.ci_high}
            metrics[kind]["ground"] = {**g.metrics(), "first_pass_depth_m": first.depth_m,
                                       "first_pass_rate_mm_h": configured_rate}
            sky = fit_light(clear_light, frame_lights(ds, ds.ids(kind), kind, params.run.show_progress), kind, params)
            if sky is not None:
                light[kind] = sky.rates_entry()
                metrics[kind]["overcast"] = sky.metrics()
                print(f"calibrate_precipitation {kind} light: zenith {sky.zenith_luminance:.3g} "
                      f"[{sky.zenith_ci[0]:.3g}, {sky.zenith_ci[1]:.3g}], zeta {sky.zenith_over_surface:.3g}, "
                      f"diffuse gain {sky.diffuse_gains[0]:.3g} (T = 0) to {sky.diffuse_gains[-1]:.3g} "
                      f"(T = {sky.sun_grid[-1]:g}); sun transmittance not identified")
            metrics[kind]["seconds"] = round(time.time() - t_kind, 2)
            print(f"calibrate_precipitation {kind} ground: {1000 * g.depth_m:.3g} mm [{1000 * g.ci_low:.3g}, "
                  f"{1000 * g.ci_high:.3g}] ({g.statistic}: reference {g.reference_mean:.4g})"
                  + ("; WARNING: outside the simulated grid, widen its depths" if g.beyond_grid else ""))
        if not kinds:
            print(f"calibrate_precipitation: reference {ds.root} has no snow or rain split; the particles params' "
                  f"rates stay in force")
        atomic.write_json(params.paths.data / PRECIPITATION_RATES_FILE,
                          {**rates, "ground": ground, "overcast": light, "reference_root": str(ds.root),
                           "reference_source": params.reference.source},
                          indent=2)
        figure = tracker.reports / "rates.png"
        if fits:
            fig = rates_figure(fits, reference, simulated,
                               {kind: metrics[kind]["rate_grid_ground_depth_m"] for kind in fits})
        else:
            fig, ax = plt.subplots(figsize=(5, 2))
            ax.text(0.5, 0.5, "no snow or rain split in the reference", ha="center", va="center")
            ax.axis("off")
        fig.savefig(figure, dpi=100)
        plt.close(fig)
        tracker.log_artifact(figure, "figures")
        if ground_fits:
            figure = tracker.reports / "ground.png"
            fig = ground_figure(ground_fits, ground_reference, ground_simulated)
            fig.savefig(figure, dpi=100)
            plt.close(fig)
            tracker.log_artifact(figure, "figures")
        metrics["seconds"] = round(time.time() - t0, 2)
        tracker.finish(metrics, headline(metrics), logged={"seconds": metrics["seconds"]}, children={
            kind: ({"weather": kind, "severity": f"{rates[kind]['rate_mm_h']:.3g} mm/h"},
                   {k: v for k, v in metrics[kind].items() if isinstance(v, (int, float))}) for kind in kinds})
    return metrics


def main(argv: list[str] | None = None) -> dict:
    params = parse_stage_args("calibrate_precipitation", argv)
    return run_stage(calibrate_precipitation_flow, params)


if __name__ == "__main__":
    main()
