"""The summary's Markdown, built from the stages' figures (``reports/<stage>/details.json``); no file I/O here.

Every number comes from a metrics dict; the paper's figures (`PAPER_TABLE1`, and Tables 2 and 3 inside the detect
stage's tables) are shown beside ours and labelled as the paper's real-data figures, never used to tune anything.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from weatheralign.verify.table import PAPER_TABLE1


def _num(value: Any, fmt: str = ".3f") -> str:
    return "—" if value is None else format(value, fmt)


def reprojection_table(simulate: dict[str, Any]) -> str:
    """Per simulated variant (``reports/simulate_summary/details.json``): the re-projection error of the particles the
    LiDAR saw, projected into every camera that drew them [px], and what the weather did to the LiDAR points; the
    paper's figures beside (snow and rain only: it has none for fog)."""
    lines = ["| variant | re-projection mean [px] | max [px] | pairs | points lost | points scattered | "
             "paper mean / max [px] |", "| --- | ---: | ---: | ---: | ---: | ---: | --- |"]
    for name, m in simulate.items():
        if not isinstance(m, dict) or "points_lost" not in m:
            continue
        total = sum(m.get(k, 0) for k in ("points_unchanged", "points_attenuated", "points_scattered",
                                          "points_lost"))
        weather = name.rsplit("-", 1)[0]
        paper = PAPER_TABLE1["reprojection_mean_px"].get(weather)
        paper_txt = (f"{paper} / {PAPER_TABLE1['reprojection_max_px'][weather]}" if paper is not None and
                     name.endswith("-aligned") else "—")
        pairs = m.get("reprojection_pairs", 0)
        lines.append(f"| {name} | {_num(m.get('reprojection_mean_px') if pairs else None, '.4f')} | "
                     f"{_num(m.get('reprojection_max_px') if pairs else None, '.4f')} | {pairs} | "
                     f"{m['points_lost'] / max(total, 1):.2%} | {m.get('points_scattered', 0) / max(total, 1):.2%} "
                     f"| {paper_txt} |")
    return "\n".join(lines)


def redam_table(calibrate: dict[str, Any], truth: dict[str, Any] | None) -> str:
    """ReDAM per fog level (``reports/calibrate_fog/details.json``): the tuned LiDAR parameters (α with its
    frame-bootstrap interval), D_KS with its interval, the camera's check (KID, visibility ratio, the fog's airlight
    gain over the clear sky), and, for the synthetic reference, the hidden truth it was tuned blind to (relative
    error of the tuned α)."""
    lines = ["| level | tuned α [1/m] [interval] | hidden α [1/m] | α error | tuned β [1/(m sr)] | hidden β | "
             "D_KS [interval] | KID | camera visibility ratio | airlight gain (median) |",
             "| --- | --- | ---: | ---: | ---: | ---: | --- | ---: | ---: | ---: |"]
    for level, m in calibrate.items():
        if not isinstance(m, dict) or "alpha" not in m:
            continue
        hidden = (truth or {}).get(level, {})
        err = (m["alpha"] / hidden["alpha"] - 1.0) if hidden.get("alpha") else None
        interval = f" [{m['alpha_ci_low']:.4g}, {m['alpha_ci_high']:.4g}]" if "alpha_ci_low" in m else ""
        lines.append(f"| {level} | {m['alpha']:.4g}{interval} | {_num(hidden.get('alpha'), '.4g')} | "
                     f"{'—' if err is None else f'{err:+.1%}'} | {m['beta']:.3g} | {_num(hidden.get('beta'), '.3g')} "
                     f"| {m['ks']:.4f} [{m['ks_ci_low']:.4f}, {m['ks_ci_high']:.4f}] | {_num(m.get('kid'), '.4f')} | "
                     f"{_num(m.get('camera_visibility_ratio'))} | {_num(m.get('airlight_gain_median'))} |")
    return "\n".join(lines)


def rate_table(calibrate: dict[str, Any], truth: dict[str, Any] | None) -> str:
    """ReDAM for snow and rain (``reports/calibrate_precipitation/details.json``): per weather the tuned rate with
    its frame-bootstrap interval, the reference's open-path echo rate it was matched on, and, for the synthetic
    reference, the hidden rate it was tuned blind to (relative error; whether the interval holds it)."""
    lines = ["| weather | tuned rate [mm/h] [interval] | hidden rate [mm/h] | error | interval holds it | "
             "echo rate matched (reference) | beyond the grid |", "| --- | --- | ---: | ---: | --- | ---: | --- |"]
    for kind in calibrate.get("kinds", []):
        m = calibrate.get(kind)
        if not isinstance(m, dict) or "rate_mm_h" not in m:
            continue
        hidden = (truth or {}).get(kind, {}).get("rate_mm_h")
        err = m["rate_mm_h"] / hidden - 1.0 if hidden else None
        holds = "—" if hidden is None else ("yes" if m["rate_ci_low"] <= hidden <= m["rate_ci_high"] else "no")
        lines.append(f"| {kind} | {m['rate_mm_h']:.3g} [{m['rate_ci_low']:.3g}, {m['rate_ci_high']:.3g}] | "
                     f"{_num(hidden, '.4g')} | {'—' if err is None else f'{err:+.1%}'} | {holds} | "
                     f"{m['open_path_echo_rate_reference']:.4g} | {'yes' if m.get('beyond_grid') else 'no'} |")
    return "\n".join(lines)


_FINDING_PATTERNS: list[tuple[str, str]] = [
    (r"pretrained:(?P<w>[^:]+):unaligned-aligned:(?P<m>\w+)",
     "evaluating the pretrained detector on unaligned instead of aligned {w} changes its {M} by"),
    (r"pretrained:clean:fused-lidar:(?P<m>\w+)", "the camera adds to the LiDAR-only detector's clean {M}"),
    (r"pretrained:clean:fused-camera:(?P<m>\w+)", "the LiDAR adds to the camera-only detector's clean {M}"),
    (r"pretrained:clean:fused-shuffled_images:(?P<m>\w+)",
     "each sample's own images instead of another sample's add to the clean {M}"),
    (r"pretrained:(?P<w>[^:]+):clean-aligned_cameras:(?P<m>\w+)",
     "the clean {M} minus that with aligned {w} on the cameras only (clean LiDAR) is"),
    (r"pretrained:(?P<w>[^:]+):unaligned_cameras-aligned_cameras:(?P<m>\w+)",
     "with clean LiDAR, unaligned instead of aligned {w} cameras change the {M} by"),
    (r"finetuned-(?P<w>[^:]+)-mix-vs-pretrained:clean:(?P<m>\w+)",
     "finetuning on the {w} mix changes the clean {M} by"),
    (r"finetuned-(?P<w>[^:]+)-aligned-vs-unaligned:[^:]+:(?P<m>\w+)",
     "finetuning on aligned instead of unaligned {w} changes the {M} on aligned {w} by"),
    (r"finetuned-(?P<w>[^:]+)-vs-pretrained:[^:]+:(?P<m>\w+)",
     "finetuning on aligned {w} changes the {M} on aligned {w} by"),
]


def findings(detect: dict[str, Any]) -> list[str]:
    """One sentence per paired difference of the detect stage (``differences``), generated from its numbers: the
    difference, its bootstrap interval (seeds x scene blocks) and whether the interval excludes 0 (the difference
    exceeds the evaluation's sampling noise) — those first."""
    out: list[tuple[bool, str]] = []
    for key, d in detect.get("differences", {}).items():
        phrase = f"{d['metric']} of {d['a']} minus {d['b']}:"
        for pattern, template in _FINDING_PATTERNS:
            if (m := re.fullmatch(pattern, key)) is not None:
                groups = m.groupdict()
                phrase = template.format(w=groups.get("w", ""), M={"map": "mAP", "nds": "NDS"}.get(groups["m"],
                                                                                                  groups["m"]))
                break
        lo, hi = d["ci"]
        verdict = "exceeds the noise" if d["exceeds_noise"] else "within the noise"
        out.append((bool(d["exceeds_noise"]),
                    f"{phrase[0].upper()}{phrase[1:]} {d['difference']:+.3f} [{lo:+.3f}, {hi:+.3f}] ({verdict})"))
    return [text for exceeds, text in sorted(out, key=lambda x: not x[0])]


@dataclass(frozen=True)
class StageCost:
    """What one stage cost in its latest tracked run: wall seconds (None: not tracked) and its outputs' disk use
    [bytes] (hard links counted once)."""

    stage: str
    seconds: float | None
    disk_bytes: int | None


@dataclass(frozen=True)
class StageSource:
    """Where a stage's figures came from: its latest finished MLflow stage run (name and UI page) and the DVC
    experiment it ran in (``workspace`` for a plain ``dvc repro``)."""

    stage: str
    run_name: str
    run_url: str
    dvc_experiment: str


def source_line(sources: dict[str, StageSource], *stages: str, earlier: frozenset[str] = frozenset(),
                outdated: Mapping[str, Sequence[str]] | None = None) -> str:
    """One Markdown line naming, for each of ``stages`` with a known source, its MLflow run (a link) and its DVC
    experiment, for each in ``earlier`` (figures present but no run of it in this tracking store) that it comes from
    an earlier run, and for each in ``outdated`` (`outdated_inputs`) the datasets that changed since it read them;
    empty when none of these (tracking off, inputs current)."""
    outdated = outdated or {}
    items = [f"`{s.stage}`: MLflow run [{s.run_name}]({s.run_url}), DVC experiment `{s.dvc_experiment}`"
             for s in (sources[name] for name in stages if name in sources)]
    items += [f"`{name}`: an earlier run, not in this MLflow store (its inputs may differ from this run's: "
              "`dvc status` lists what to rerun)" for name in stages if name in earlier and name not in sources]
    items += [f"`{name}`: computed from an earlier version of {_names(outdated[name])} (`dvc repro` reruns it)"
              for name in stages if name in outdated]
    return "*From " + "; ".join(items) + ".*" if items else ""


def _names(names: Sequence[str]) -> str:
    return ", ".join(f"`{n}`" for n in names)


def earlier_stages(metrics: dict[str, dict[str, Any]], sources: dict[str, StageSource]) -> frozenset[str]:
    """The stages whose figures ``metrics`` holds but whose run this tracking store does not (an earlier run's
    reports, e.g. after a rerun of some stages only); none without tracking (``sources`` empty)."""
    return frozenset(name for name in metrics if sources and name not in sources)


def outdated_inputs(metrics: dict[str, dict[str, Any]], digests: Mapping[str, str]) -> dict[str, tuple[str, ...]]:
    """Per stage whose figures record the datasets they were computed from (``input_digests``: manifest name ->
    content digest) the names of those whose current manifest (``digests``, the same mapping) differs or is gone;
    stages whose inputs are all current are left out."""
    out = {}
    for stage, figures in metrics.items():
        changed = tuple(name for name, digest in sorted(figures.get("input_digests", {}).items())
                        if digests.get(name) != digest)
        if changed:
            out[stage] = changed
    return out


def cost_table(costs: list[StageCost]) -> str:
    """The stages' wall time and disk use, with totals."""
    lines = ["| stage | wall time | disk |", "| --- | ---: | ---: |"]
    for c in costs:
        lines.append(f"| {c.stage} | {'—' if c.seconds is None else f'{c.seconds / 60:.1f} min'} | "
                     f"{'—' if c.disk_bytes is None else f'{c.disk_bytes / 1e9:.2f} GB'} |")
    secs = [c.seconds for c in costs if c.seconds is not None]
    disk = [c.disk_bytes for c in costs if c.disk_bytes is not None]
    lines.append(f"| **total** | {sum(secs) / 60:.1f} min | {sum(disk) / 1e9:.2f} GB |")
    return "\n".join(lines)


def summary_markdown(metrics: dict[str, dict[str, Any]], truth: dict[str, Any] | None, detect_tables: list[str],
                     figures: dict[str, str], costs: list[StageCost],
                     sources: dict[str, StageSource] | None = None, digests: Mapping[str, str] | None = None) -> str:
    """The whole summary. ``metrics``: per stage (``world``, ``calibrate_fog``, ``simulate``, ``detect``) its
    figures (``details.json``; a missing stage: its section says so); ``truth``: the reference's sealed truth (None
    for real data); ``detect_tables``: the detect stage's Markdown tables (Tables 2 and 3); ``figures``: caption ->
    image path relative to the summary; ``costs``: per stage; ``sources``: per stage its MLflow run and DVC
    experiment, named under each table; ``digests``: manifest name -> content digest of the datasets as they are now
    (`outdated_inputs`; None: not checked)."""
    sources = sources or {}
    earlier = earlier_stages(metrics, sources)
    outdated = outdated_inputs(metrics, digests) if digests is not None else {}
    world = metrics.get("world", {})
    provenance = ("Every figure below is computed by this run" if not earlier and not outdated else
                  "Every figure below is computed by the run named under its table")
    if earlier:
        provenance += f"; those of {_names(sorted(earlier))} come from an earlier run whose inputs may differ from " \
                      "this run's"
    provenance += "".join(f"; **the figures of `{stage}` are computed from an earlier version of {_names(names)}**, "
                          "simulated again since (`dvc repro` reruns it)" for stage, names in sorted(outdated.items()))
    parts = ["# weatheralign: run summary", "",
             f"Dataset: {world.get('source', '?')} world, {world.get('num_scenes', '?')} scenes, "
             f"{world.get('num_samples', '?')} keyframe samples, {world.get('num_sweeps', '?')} sweeps. {provenance}; "
             "the paper's figures (real nuScenes-mini and Seeing Through Fog data) are shown beside ours for "
             "comparison and labelled as the paper's.", ""]
    parts += ["## Findings", "",
              "Generated from the detect stage's paired bootstrap intervals (training seeds x scene blocks) "
              f"({metrics.get('detect', {}).get('confidence', 0.95):.0%}); those exceeding the noise first.", ""]
    found = findings(metrics.get("detect", {}))
    parts += [f"- {f}" for f in found] if found else ["- (no detect metrics in this run)"]
    if found and ("detect" in earlier or "detect" in outdated):
        parts += ["", source_line(sources, "detect", earlier=earlier, outdated=outdated)]
    verify = metrics.get("verify", {})
    mmd_half = (re.sub(r"^(#+) ", r"##\1 ", verify["table_markdown"], flags=re.MULTILINE) if "table_markdown" in verify
                else "The MMD of fused features (the paper's second half of Table 1) needs the `verify` stage, which "
                     "did not run: not measured.")
    parts += ["", "## Table 1: alignment of the weather across sensors", "",
              "Re-projection: each particle the LiDAR saw, projected into every camera that drew it, against where the "
              "camera drew it.", "",
              reprojection_table(metrics.get("simulate", {})), "", mmd_half, "",
              source_line(sources, "simulate", "verify", earlier=earlier, outdated=outdated), "",
              "## ReDAM: fog severity tuned to the reference", "",
              "The LiDAR fog parameters tuned so that the simulated intensity distribution matches the reference's "
              "(two-sample Kolmogorov-Smirnov distance, frame-bootstrap interval); the cameras get the same α. For "
              "the synthetic reference, the hidden levels it was tuned blind to are beside.", "",
              redam_table(metrics.get("calibrate_fog", {}), truth), "",
              source_line(sources, "calibrate_fog", earlier=earlier, outdated=outdated), ""]
    if "calibrate_precipitation" in metrics:
        parts += ["## ReDAM for snow and rain: rates tuned to the reference", "",
                  "The snow and rain rates tuned so that the fast simulator's statistic "
                  f"({metrics['calibrate_precipitation'].get('statistic', 'an echo rate')}) matches the reference's "
                  "(frame-bootstrap interval). For the synthetic reference, the hidden rates it was tuned blind to "
                  "are beside.", "", rate_table(metrics["calibrate_precipitation"], truth), "",
                  source_line(sources, "calibrate_precipitation", earlier=earlier, outdated=outdated), ""]
    for table in detect_tables:
        parts += [re.sub(r"^(#+) ", r"#\1 ", table, flags=re.MULTILINE), "",  # one level below the summary
                  source_line(sources, "detect", earlier=earlier, outdated=outdated), ""]
    parts += ["## Figures", ""]
    parts += [f"![{caption}]({path})\n\n*{caption}*\n" for caption, path in figures.items()]
    parts += ["## What the run cost", "", "Wall time of each stage's latest tracked run (MLflow) and the disk its "
              "outputs take.", "", cost_table(costs), ""]
    return "\n".join(parts)
