"""Env throughput before and after a change, from two stored runs of env_throughput.py.

Both runs must come from the same machine, back to back (this script checks the CPU
names match). Writes docs/benchmarks/env_throughput_comparison.md: for each env and
configuration the two median rates and their ratio.

    python benchmarks/speed/compare_env_throughput.py BEFORE.json AFTER.json [--label-before TEXT] [--label-after TEXT]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from heml_gym.benchmarks.common import RESULTS, markdown_table

KEYS = ("env", "actions", "num_envs", "threads", "omp_wait_policy")


def compare(before: dict, after: dict, label_before: str, label_after: str) -> str:
    if before["machine"]["cpu"] != after["machine"]["cpu"]:
        raise SystemExit(f"the runs come from different CPUs ({before['machine']['cpu']} / "
                         f"{after['machine']['cpu']}): rerun them back to back on one machine")
    lines = [f"Env steps per second (medians), {label_before} against {label_after}, run back to back on "
             f"{after['machine']['cpu']} ({after['machine']['cores']} cores), {after['machine']['date']} "
             "(`benchmarks/speed/compare_env_throughput.py` on the two stored runs of `benchmarks/speed/env_throughput.py`).\n"]
    for env_id, data in after["envs"].items():
        old_rows = before["envs"].get(env_id, {}).get("throughput", [])
        rows = []
        for r in data["throughput"]:
            match = [o for o in old_rows if all(o[k] == r[k] for k in KEYS)]
            if not match:
                continue
            o = match[0]
            rows.append([r["env"], r["actions"], r["num_envs"], r["threads"],
                         f"{o['median_steps_per_s']:.0f} ± {o['iqr_steps_per_s']:.0f}",
                         f"{r['median_steps_per_s']:.0f} ± {r['iqr_steps_per_s']:.0f}",
                         f"{r['median_steps_per_s'] / o['median_steps_per_s']:.2f}"])
        lines.append(f"\n### {env_id}\n\n" + markdown_table(
            ["env", "actions", "N", "threads", f"{label_before} (median ± IQR)", f"{label_after} (median ± IQR)",
             "ratio"], rows))
    lines.append("\nA ratio whose two rates lie within each other's IQR is noise on a 2-core machine shared with "
                 "the benchmark's own threads; re-run a row before reading a change into it.")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before")
    ap.add_argument("after")
    ap.add_argument("--label-before", default="before")
    ap.add_argument("--label-after", default="after")
    args = ap.parse_args(argv)
    text = compare(json.loads(Path(args.before).read_text()), json.loads(Path(args.after).read_text()),
                   args.label_before, args.label_after)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "env_throughput_comparison.md").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
