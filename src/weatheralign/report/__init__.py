"""The run's summary for a reader: ``reports/summary.md`` and the same as one self-contained HTML page.

`summary` builds the Markdown from the stages' metrics (pure functions of the metrics dicts: the paper's Table 1 with
ours beside it, the ReDAM results against the reference's hidden truth, the detector's Tables 2 and 3 as the detect
stage wrote them, findings generated from the paired intervals, what the run cost); `html` turns it into one page
with every figure embedded and nothing loaded from the network.
"""

from weatheralign.report.html import markdown_to_html
from weatheralign.report.summary import (
    PAPER_TABLE1,
    StageCost,
    StageSource,
    cost_table,
    earlier_stages,
    findings,
    outdated_inputs,
    rate_table,
    redam_table,
    reprojection_table,
    source_line,
    summary_markdown,
)

__all__ = ["PAPER_TABLE1", "StageCost", "StageSource", "cost_table", "earlier_stages", "findings", "markdown_to_html",
           "outdated_inputs", "rate_table", "redam_table", "reprojection_table", "source_line", "summary_markdown"]
