"""The paper's Table 1 ("Re-projection error and MMD distance") regenerated from `verify`'s metrics, beside the
paper's own figures (measured on real nuScenes weather; labelled as such, never compared as targets)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

PAPER_TABLE1: dict[str, dict[str, float | None]] = {
    "reprojection_mean_px": {"fog": None, "snow": 0.7632, "rain": 0.7641},
    "reprojection_max_px": {"fog": None, "snow": 1.3843, "rain": 1.411},
    "mmd_aligned": {"fog": 0.2837, "snow": 0.3065, "rain": 0.1870},
    "mmd_unaligned": {"fog": 0.3491, "snow": 0.3607, "rain": 0.1870},
}
"""The paper's Table 1 (its MMD convention is not stated; ours: unbiased MMD², see `weatheralign.verify.mmd`)."""

WEATHER_OF: dict[str, str] = {"fog_light": "fog", "fog_dense": "fog", "snow": "snow", "rain": "rain"}


def _num(value: Any, digits: int = 4) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def _p(value: Any) -> str:
    return "–" if value is None else f"{value:.3g}"


def _ci(pair: Any) -> str:
    return "" if not pair else f" [{pair[0]:.3f}, {pair[1]:.3f}]"


def _kid(c: Mapping[str, Any]) -> str:
    spread = f" ± {_num(c['kid_std'])}" if c.get("kid_std", 0.0) > 1e-9 else ""  # all frames in one subset: none
    return f"{_num(c['kid'])}{spread} ({c['kid_backbone']})"


def _sources(severity: Mapping[str, Any]) -> str:
    rates = severity.get("rates") or {}
    return ", ".join(f"{k} {v}" for k, v in rates.items()) or "params"


def _rejected(metrics: Mapping[str, Any]) -> str:
    """The trainings that did not fit their training frames and were replaced, as a clause ('' when none)."""
    rejected = metrics.get("classifiers_rejected") or []
    if not rejected:
        return ""
    each = ", ".join(f"seed {r['seed']}: {r['train_accuracy']:.2f}" for r in rejected)
    return f"; {len(rejected)} training(s) replaced for fitting their own training frames poorly ({each})"


def table_markdown(metrics: Mapping[str, Any]) -> str:
    """Markdown: ours per verified condition (re-projection, MMD² aligned / unaligned with p-values and intervals,
    the paired difference, the control, D_KS, KID), then the paper's real-data row per weather."""
    conditions: Mapping[str, Mapping[str, Any]] = metrics["conditions"]
    names = list(conditions)
    lines = ["# Table 1 regenerated: re-projection error and MMD of fused features", "",
             f"Reference: `{metrics.get('reference_source')}` ({metrics.get('reference_root')}); severity: fog levels "
             f"from {metrics['severity']['fog_levels']}, snow {metrics['severity']['snow_rate_mm_h']:.3g} mm/h, rain "
             f"{metrics['severity']['rain_rate_mm_h']:.3g} mm/h (rates: {_sources(metrics['severity'])}). "
             f"{metrics.get('classifiers', 1)} weather classifier(s), held-out accuracy "
             f"{metrics['classifier_accuracy']:.3f} ({metrics['classifier_held_out']} frames){_rejected(metrics)}. "
             "MMD² is the unbiased "
             "estimator on the classifiers' fused features (Gaussian kernel, median heuristic on the pooled, "
             "standardised features of each classifier, the kernels averaged over the classifiers); p: permutation "
             "p-value; brackets: bootstrap interval over frames and classifiers (their training noise included); "
             "the range of the classifiers' own MMD² (aligned, unaligned) in its row; the control is a paired test "
             "(a frame's camera with its own LiDAR and with another frame's; the p-value of each classifier alone in "
             "brackets). Unaligned: the camera sees independent media of its own severity (fog: α drawn between "
             "the levels; snow / rain: another field at a rate within a factor of the LiDAR's); for snow and rain "
             "also the positions alone (the unaligned camera at the LiDAR's rate).", "",
             "## Ours", "",
             "| | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]

    def row(label: str, cell) -> None:
        lines.append(f"| {label} | " + " | ".join(cell(conditions[n]) for n in names) + " |")

    row("re-projection mean [px] (simulate)", lambda c: _num(c.get("reprojection_mean_px")))
    row("re-projection max [px] (simulate)", lambda c: _num(c.get("reprojection_max_px")))
    row("re-projection mean [px] (reference frames)", lambda c: _num(c.get("reference_reprojection_mean_px")))
    row("MMD² aligned", lambda c: f"**{_num(c['mmd_aligned'])}**{_ci(c.get('mmd_aligned_ci'))} "
                                  f"(p {_p(c['mmd_p_aligned'])})")
    row("MMD² unaligned", lambda c: f"{_num(c['mmd_unaligned'])}{_ci(c.get('mmd_unaligned_ci'))} "
                                    f"(p {_p(c['mmd_p_unaligned'])})")
    if any(len(c.get("mmd_aligned_each_classifier", ())) > 1 for c in conditions.values()):
        row("MMD² of each classifier alone: aligned; unaligned", lambda c: "; ".join(
            f"{_num(min(c[k]))}..{_num(max(c[k]))}" if c.get(k) else "—"
            for k in ("mmd_aligned_each_classifier", "mmd_unaligned_each_classifier")))
    row("aligned − unaligned (paired)", lambda c: f"{c['mmd_difference']:+.4f}{_ci(c.get('mmd_difference_ci'))} "
                                                  f"(p {_p(c['mmd_difference_p'])})")
    if any("mmd_unaligned_positions" in c for c in conditions.values()):
        row("MMD² unaligned, positions alone (same rate)",
            lambda c: "—" if "mmd_unaligned_positions" not in c else
            f"{_num(c['mmd_unaligned_positions'])}{_ci(c.get('mmd_unaligned_positions_ci'))} "
            f"(p {_p(c['mmd_p_unaligned_positions'])})")
        row("aligned − positions alone (paired)",
            lambda c: "—" if "mmd_difference_positions" not in c else
            f"{c['mmd_difference_positions']:+.4f}{_ci(c.get('mmd_difference_positions_ci'))} "
            f"(p {_p(c['mmd_difference_positions_p'])})")
    row("control: broken pairs", lambda c: f"{_num(c['control_mmd'])} (p {_p(c['control_p'])})" + (
        " [" + ", ".join(_p(p) for p in c["control_p_each_classifier"]) + "]"
        if len(c.get("control_p_each_classifier", ())) > 1 else ""))
    row("LiDAR D_KS vs reference", lambda c: f"{_num(c['ks'])} [{c['ks_ci_low']:.3f}, {c['ks_ci_high']:.3f}]")
    row("camera KID", _kid)
    row("camera visibility ratio", lambda c: _num(c.get("camera_visibility_ratio"), 3))
    weathers = list(dict.fromkeys(WEATHER_OF.get(n, n) for n in names))
    lines += ["", "## The paper (real nuScenes weather; not targets)", "",
              "| | " + " | ".join(weathers) + " |", "|---|" + "---|" * len(weathers)]
    for key, label in (("reprojection_mean_px", "re-projection mean [px]"),
                       ("reprojection_max_px", "re-projection max [px]"),
                       ("mmd_aligned", "MMD aligned"), ("mmd_unaligned", "MMD unaligned")):
        lines.append(f"| {label} | " + " | ".join(_num(PAPER_TABLE1[key].get(w)) for w in weathers) + " |")
    return "\n".join(lines) + "\n"


__all__ = ["PAPER_TABLE1", "table_markdown"]
