"""The zoo table of BENCHMARKS.md (section 10) from a `nerfbot bench` folder: one row per scene and
method, one column group per budget, the best PSNR of a scene and budget in bold, and how far
`auto` is from that best.

usage: python docs/benchmarks/zoo_table.py BENCH_DIR
  e.g. nerfbot bench --data tabletop,workspace:4 --methods ngp,plenoxels,tensorf,auto \\
           --budgets 60,180 --no-chamfer --out B/zoo && python docs/benchmarks/zoo_table.py B/zoo

Depth MAE is printed in mm below 0.1 m, in m above. `auto`'s row names what it chose (its runs'
``auto.json``: method and options).
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


def auto_choices(bench: Path) -> dict:
    """scene -> "method, option value, ..." of the `auto` runs (from their ``auto.json``)."""
    out = {}
    for point in sorted(bench.glob("runs/*/point.json")):
        p = json.loads(point.read_text())
        choice = point.parent / "auto.json"
        if p.get("method") != "auto" or not choice.exists():
            continue
        c = json.loads(choice.read_text())
        opts = ", ".join(f"{k} {v}" for k, v in sorted(c.get("options", {}).items()))
        out[p["scene"]] = c["method"] + (f", {opts}" if opts else "")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bench", type=Path, help="a `nerfbot bench --out` folder")
    args = ap.parse_args()
    rows = [r for r in json.loads((args.bench / "bench.json").read_text())["summary"]
            if r.get("budget_kind", "seconds") == "seconds"]
    budgets = sorted({r["budget"] for r in rows})
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    for r in rows:  # a swept option makes its own row
        r["label"] = r["method"] + (f" {r['options']}" if r.get("options") else "")
    methods = list(dict.fromkeys(r["label"] for r in rows))
    cell = {(r["scene"], r["label"], r["budget"]): r for r in rows}
    best = {(s, b): max((cell[s, m, b]["psnr"] for m in methods if (s, m, b) in cell), default=None)
            for s in scenes for b in budgets}
    chosen = auto_choices(args.bench)

    head = "| scene | method | " + " | ".join(
        f"{b:g} s: PSNR / non-sky / objects | depth MAE | render ms | steps/s" for b in budgets) + " |"
    print(head)
    print("|" + "---|" * (2 + 4 * len(budgets)))
    for s in scenes:
        for m in methods:
            name = f"`auto` ({chosen[s]})" if m == "auto" and s in chosen else m
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
            print(f"| `{s}` | {name} | " + " | ".join(cells) + " |")
    if "auto" in methods:
        print()
        for b in budgets:
            gaps = []
            for s in scenes:
                r = cell.get((s, "auto", b))
                if r is not None and best[s, b] is not None:
                    leader = max((m for m in methods if (s, m, b) in cell),
                                 key=lambda m: cell[s, m, b]["psnr"])
                    gaps.append(f"{s} {r['psnr'] - best[s, b]:+.2f} ({leader})")
            print(f"- auto - best at {b:g} s: " + ", ".join(gaps))


if __name__ == "__main__":
    main()
