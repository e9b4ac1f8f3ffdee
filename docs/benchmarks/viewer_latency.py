"""How quickly does ``nerfbot view`` answer a browser on this machine?

usage: python docs/benchmarks/viewer_latency.py RUN [RUN ...] [--moves 8]
                                                [--viewport 960 540] [--json OUT.json]
                                                [--supersample-pattern grid|corners|adaptive]

For each run, the viewer of ``nerfbot view RUN`` (built by the command's own code, in this
process) is opened by headless Chromium (the system's, driven by playwright), which then drags
the camera ``--moves`` times: a 0.3 s mouse drag on the canvas, then stillness until the full
frame arrives. Measured on the viewer's side, per run:

- first frame: seconds from the browser's connection to the first frame sent (a preview, a
  quarter of the resolution per side, one ray per pixel) and to the first full frame (the
  training images' height, the run's rays per pixel);
- preview frames while the camera moves: render milliseconds (median);
- full frames: render milliseconds (median), and seconds from the camera's last move to the
  full frame sent (median; includes the viewer's 0.3 s wait for stillness).

Each run is measured in a fresh process (its first frame pays what a fresh ``nerfbot view``
pays, e.g. loading the numba kernels). The browser runs on the same two cores (software WebGL),
as a browser on a robot's computer would; its share is in the times. ``--supersample-pattern``
sets the runs' render option (the pattern of their full frames) instead of their own.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from playwright.sync_api import sync_playwright

from nerfbot.app.cli import build_parser, make_viewer


def measure(run: Path, moves: int, viewport: tuple[int, int], chromium: str,
            pattern: str | None = None) -> dict:
    args = build_parser().parse_args(["view", str(run), "--port", "0", "--no-cameras"])
    viewer = make_viewer(args)
    if pattern is not None:
        config = getattr(viewer.model, "config", None)
        if config is None or not hasattr(config, "supersample_pattern"):
            raise SystemExit(f"{run}: its renderer has no supersample_pattern option")
        config.supersample_pattern = pattern
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium,
                                         args=["--enable-unsafe-swiftshader",
                                               "--use-angle=swiftshader"])
            page = browser.new_page(viewport={"width": viewport[0], "height": viewport[1]})
            page.goto(f"http://127.0.0.1:{viewer.port}")
            first_full = viewer.wait_for_frames(1, "full", timeout=300)[0]
            (cid, connected), = viewer.connected_at.items()
            first = min(s.sent_at for s in viewer.stats if s.client == cid)
            x0, y0 = int(0.35 * viewport[0]), int(0.7 * viewport[1])
            for k in range(moves):
                done = len([s for s in viewer.stats if s.kind == "full"])
                page.mouse.move(x0, y0)
                page.mouse.down()
                dx = 60 if k % 2 == 0 else -60
                for step in range(1, 11):
                    page.mouse.move(x0 + dx * step / 10, y0 - 2 * step)
                    time.sleep(0.03)
                page.mouse.up()
                viewer.wait_for_frames(done + 1, "full", timeout=300)
            browser.close()
    finally:
        viewer.stop()
    stats = viewer.stats[:]
    previews = [s for s in stats if s.kind == "preview"]
    fulls = [s for s in stats if s.kind == "full"][1:]  # after the first
    return {
        "run": str(run), "first_frame_s": first - connected,
        "first_full_frame_s": first_full.sent_at - connected,
        "preview_px": f"{previews[0].width}x{previews[0].height}" if previews else None,
        "preview_render_ms": 1e3 * statistics.median(s.render_s for s in previews),
        "previews": len(previews),
        "full_px": f"{first_full.width}x{first_full.height}",
        "full_render_ms": 1e3 * statistics.median(s.render_s for s in fulls),
        "full_after_stop_s": statistics.median(s.since_change_s for s in fulls),
        "moves": len(fulls),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", type=Path, nargs="+")
    p.add_argument("--moves", type=int, default=8)
    p.add_argument("--viewport", type=int, nargs=2, default=(960, 540), metavar=("W", "H"))
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--supersample-pattern", default=None, choices=("grid", "corners", "adaptive"))
    p.add_argument("--single", action="store_true", help=argparse.SUPPRESS)  # one run, JSON out
    args = p.parse_args(argv)
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("needs Chromium (apt-get install chromium)")
    if args.single:
        print(json.dumps(measure(args.runs[0], args.moves, tuple(args.viewport), chromium,
                                 args.supersample_pattern)))
        return 0
    rows = []
    for run in args.runs:
        pattern = [] if args.supersample_pattern is None else \
            ["--supersample-pattern", args.supersample_pattern]
        done = subprocess.run([sys.executable, __file__, str(run), "--single", "--moves",
                               str(args.moves), "--viewport", *map(str, args.viewport), *pattern],
                              capture_output=True, text=True, check=True)
        rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    print("| run | first frame s | first full frame s | preview px | preview render ms "
          "| full px | full render ms | full frame after stop s |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {Path(r['run']).name} | {r['first_frame_s']:.2f} | "
              f"{r['first_full_frame_s']:.2f} | {r['preview_px']} | "
              f"{r['preview_render_ms']:.0f} | {r['full_px']} | {r['full_render_ms']:.0f} | "
              f"{r['full_after_stop_s']:.2f} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
