"""The table of `sefa bench latency --samples ... --json`: one decision's p50 (p90) in ms per
target and number of samples drawn in one batched call, and the machine it ran on.

    python scripts/latency_table.py latency.json
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def table(report: dict) -> str:
    sizes = report["sample_sizes"]
    cells = {(d["target"], d["samples"]): f"{d['p50_ms']:.3g} ({d['p90_ms']:.3g})"
             for d in report["decisions"]}
    targets = list(dict.fromkeys(d["target"] for d in report["decisions"]))
    m = report["machine"]
    lines = [f"{report['device']} (host CPU: {m['cpu']}), torch {m['torch']}, "
             f"{report['threads']} threads: one decision, p50 (p90) ms",
             "| target | " + " | ".join(f"N = {n}" for n in sizes) + " |",
             "|---|" + "---:|" * len(sizes)]
    for t in targets:
        lines.append(f"| {Path(t).name} | " + " | ".join(cells.get((t, n), "-") for n in sizes)
                     + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(table(json.loads(Path(sys.argv[1]).read_text())))
