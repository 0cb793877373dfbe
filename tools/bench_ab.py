#!/usr/bin/env python
"""A/B a benchmark tool between an older revision and the working tree, back to back on one machine.

    python tools/bench_ab.py --base 8ed602b --rounds 3 -- tools/bench_adaptation.py --ckpt-dir runs/paper --no-compile
    python tools/bench_ab.py --base 8ed602b --new 26b90ca -- tools/bench_adaptation.py ...   # two revisions

Checks the base revision out into a temporary git worktree and runs the tool alternately there (its own copy of the
tool and the package) and here, ``--rounds`` times each (base, new, base, new, ...), each writing ``--json``. The
rows of the tool's JSON (``rows``: dicts with variant, kind, note, cases and ms_per_case) are matched by key and
the medians over rounds compared: a ratio new/base per row. The machine is shared and noisy, so the alternation
spreads any drift over both sides.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
KEY = ("variant", "kind", "note", "cases")


def run_tool(tree: str, tool_argv: list[str], out_json: str) -> list[dict]:
    env = {**os.environ, "PYTHONPATH": tree}
    cmd = [sys.executable, os.path.join(tree, tool_argv[0]), *tool_argv[1:], "--json", out_json, "--figure", ""]
    subprocess.run(cmd, cwd=ROOT, env=env, check=True, stdout=subprocess.DEVNULL)
    with open(out_json) as fh:
        return json.load(fh)["rows"]


def add_worktree(tmp: str, name: str, revision: str) -> str:
    tree = os.path.join(tmp, name)
    subprocess.run(["git", "-C", ROOT, "worktree", "add", "--detach", tree, revision], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return tree


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", required=True, help="git revision to compare against (e.g. the commit before a change)")
    parser.add_argument("--new", default=None,
                        help="git revision of the new side (default: the working tree)")
    parser.add_argument("--rounds", type=int, default=3, help="runs per side, alternating (default 3)")
    parser.add_argument("--json", help="write every round's rows and the comparison here")
    parser.add_argument("tool", nargs=argparse.REMAINDER, help="-- then the tool and its arguments")
    args = parser.parse_args(argv)
    tool = args.tool[1:] if args.tool[:1] == ["--"] else args.tool
    if not tool or args.rounds < 1:
        raise SystemExit("error: give --rounds >= 1 and the tool after --")
    with tempfile.TemporaryDirectory(prefix="bench-ab-") as tmp:
        trees = {"base": add_worktree(tmp, "base", args.base),
                 "new": ROOT if args.new is None else add_worktree(tmp, "new", args.new)}
        try:
            results = {"base": [], "new": []}
            for r in range(args.rounds):
                for side, tree in trees.items():
                    print(f"round {r + 1}/{args.rounds}: {side}", file=sys.stderr, flush=True)
                    results[side].append(run_tool(tree, tool, os.path.join(tmp, f"{side}-{r}.json")))
        finally:
            for tree in trees.values():
                if tree != ROOT:
                    subprocess.run(["git", "-C", ROOT, "worktree", "remove", "--force", tree], check=False)
    table = compare(results)
    print("| variant | kind | cases | base ms/case | new ms/case | new/base |\n|---|---|---|---|---|---|")
    for row in table:
        kind = row["kind"] + (f" ({row['note']})" if row["note"] else "")
        print(f"| {row['variant']} | {kind} | {row['cases']} | {row['base']:.4g} | {row['new']:.4g} | "
              f"{row['ratio']:.3f} |")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"base": args.base, "new": args.new or "working tree", "tool": tool, "rounds": results, "comparison": table}, fh, indent=1)


def compare(results: dict) -> list[dict]:
    """Median ms_per_case over rounds per row key on each side, and their ratio, for keys on both sides."""
    medians = {}
    for side, rounds in results.items():
        values: dict = {}
        for rows in rounds:
            for row in rows:
                values.setdefault(tuple(row[k] for k in KEY), []).append(row["ms_per_case"])
        medians[side] = {key: statistics.median(v) for key, v in values.items()}
    common = [key for key in medians["new"] if key in medians["base"]]
    return [dict(zip(KEY, key), base=medians["base"][key], new=medians["new"][key],
                 ratio=medians["new"][key] / medians["base"][key]) for key in common]


if __name__ == "__main__":
    main()
