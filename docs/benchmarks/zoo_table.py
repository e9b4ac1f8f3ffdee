"""The zoo table of BENCHMARKS.md (section 10) from a `nerfbot bench` folder: one row per scene and
method, one column group per budget, the best PSNR of a scene and budget in bold, and how far
`auto` is from that best.

usage: python docs/benchmarks/zoo_table.py BENCH_DIR
  e.g. nerfbot bench --data tabletop,workspace:4 --methods ngp,plenoxels,tensorf,auto \\
           --budgets 60,180 --no-chamfer --out B/zoo && python docs/benchmarks/zoo_table.py B/zoo

Depth MAE is printed in mm below 0.1 m, in m above. `auto`'s rows name what it chose.
"""
import argparse
import json
from pathlib import Path


def _depth(m):
    if m is None:
        return "-"
    return f"{1000 * m:.1f} mm" if m < 0.1 else f"{m:.2f} m"


def _num(x, fmt):
    return "-" if x is None else format(x, fmt)


def label(row: dict) -> str:
    """A row's name: the method and its swept options; `auto` with what it chose for the scene
    (the bench names those rows ``auto:METHOD`` with the chosen options as JSON)."""
    method, options = row["method"], row.get("options") or ""
    if method.startswith("auto:"):
        chosen = json.loads(options) if options.startswith("{") else {}
        parts = [method.split(":", 1)[1]] + [f"{k} {v}" for k, v in sorted(chosen.items())]
        return f"`auto` ({', '.join(parts)})"
    return method + (f" {options}" if options else "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bench", type=Path, help="a `nerfbot bench --out` folder")
    args = ap.parse_args()
    rows = [r for r in json.loads((args.bench / "bench.json").read_text())["summary"]
            if r.get("budget_kind", "seconds") == "seconds"]
    budgets = sorted({r["budget"] for r in rows})
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    for r in rows:  # a swept option makes its own row
        r["label"] = label(r)
    methods = list(dict.fromkeys(r["label"] for r in rows))
    cell = {(r["scene"], r["label"], r["budget"]): r for r in rows}
    best = {(s, b): max((cell[s, m, b]["psnr"] for m in methods if (s, m, b) in cell), default=None)
            for s in scenes for b in budgets}

    head = "| scene | method | " + " | ".join(
        f"{b:g} s: PSNR / non-sky / objects | depth MAE | render ms | steps/s" for b in budgets) + " |"
    print(head)
    print("|" + "---|" * (2 + 4 * len(budgets)))
    for s in scenes:
        for m in methods:
            if not any((s, m, b) in cell for b in budgets):  # auto's choice for another scene
                continue
            cells = []
            for b in budgets:
                r = cell.get((s, m, b))
                if r is None:
                    cells.append("- | - | - | -")
                    continue
                psnr = f"{r['psnr']:.2f}"
                if r["psnr"] == best[s, b]:
                    psnr = f"**{psnr}**"
                cells.append(f"{psnr} / {_num(r['psnr_non_sky'], '.2f')} / "
                             f"{_num(r['psnr_objects'], '.2f')} | {_depth(r['depth_mae_m'])} | "
                             f"{_num(r['render_ms_per_image'], '.0f')} | "
                             f"{_num(r['steps_per_second'], '.1f')}")
            print(f"| `{s}` | {m} | " + " | ".join(cells) + " |")
    if any(m.startswith("`auto`") for m in methods):
        print()
        for b in budgets:
            gaps = []
            for s in scenes:
                r = next((cell[s, m, b] for m in methods
                          if m.startswith("`auto`") and (s, m, b) in cell), None)
                if r is not None and best[s, b] is not None:
                    leader = max((m for m in methods if (s, m, b) in cell),
                                 key=lambda m: cell[s, m, b]["psnr"])
                    leader = "auto" if leader.startswith("`auto`") else leader
                    gaps.append(f"{s} {r['psnr'] - best[s, b]:+.2f} (best: {leader})")
            print(f"- auto - best at {b:g} s: " + ", ".join(gaps))


if __name__ == "__main__":
    main()
