"""Where are the moving objects? Their centres from a trained dynamic field against MuJoCo's.

    python docs/benchmarks/object_centres.py RUN [RUN ...] [--out NAME]

Each RUN is a time-conditioned run (``kplanes``, ``dnerf``, ...) trained on a ``sims`` dynamic
capture, which it finds as ``nerfbot eval`` does. For every held-out time step of the capture
and every moving object of its manifest (``objects``: geoms whose bodies move):

- the field's estimate: the run's median z-depth at the object's pixels (its segmentation,
  eroded by 1 px so that no pixel straddles its outline) in every held-out view of that step,
  back-projected to world points; their mean is the object's centre;
- the same estimate from MuJoCo's own depth maps (the capture's): what a perfect field would
  give, since the visible surface's mean is not the object's centre (a view sees the near side);
- the truth: the geom's centre from the body pose MuJoCo recorded (``states.npz``) and the
  geom's offset in its body.

For ``rigid`` runs, the centre of each body's part at the step's time (its trained track,
:meth:`nerfbot.fields.rigid.RigidField.part_centres`) is also compared with the truth, for the
objects that are their body's only geom (the track follows the body's masks, not one geom's
centre).

For runs with a scene flow (``dnerf``'s deformation, ``rigid``'s parts), the field's points of
each object are also moved to the next captured step by it (:func:`nerfbot.query.motion.
point_motion`), and their mean displacement is compared with the geom centre's in MuJoCo.

Reports per run and object the median and the largest error over time (cm) of the field's
estimate against the truth, of the depth-map estimate against the truth, and of the field's
against the depth-map estimate (the field's own share: the estimator's offset removed). Writes
``docs/benchmarks/<NAME>.png`` (per object over time: the field's share, solid, and the
field's estimate against the truth, dotted; NAME default ``object_centres``), and with
``--json FILE`` every step's figures.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import matplotlib
import mujoco
import numpy as np
import torch
from matplotlib.figure import Figure

import sims  # noqa: F401  (MUJOCO_GL before mujoco)
from nerfbot.data.run_dataset import resolve_run_dataset
from nerfbot.ops.pointcloud import depth_to_cloud
from nerfbot.query.motion import point_motion
from nerfbot.query.render import render_image
from nerfbot.train.runs import load_model
from sims.scene import load_capture_model

matplotlib.use("Agg")
HERE = Path(__file__).resolve().parent


def geom_centres(dataset) -> tuple[dict, np.ndarray]:
    """({object name: (S, 3) world centre per recorded state}, state of each frame (N,)) from
    the capture's ``states.npz`` and the scene's MJCF (each geom's offset in its body)."""
    manifest = dataset.manifest
    states = np.load(dataset.root / manifest["capture"]["state_file"])
    body_names = [str(n) for n in states["body_names"]]
    source = str(manifest.get("source") or manifest["name"])
    model, _ = load_capture_model(source.removeprefix("builtin:"))  # tossed:3, or an MJCF path
    centres = {}
    for name in manifest["objects"]:
        g = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)
        body = body_names.index(model.body(int(model.geom_bodyid[g])).name)
        quats = states["body_quat"][:, body]
        offset = np.empty((len(quats), 3))
        for s, q in enumerate(quats):
            mujoco.mju_rotVecQuat(offset[s], model.geom_pos[g], q)
        centres[name] = states["body_pos"][:, body] + offset
    return centres, states["state_of_frame"]


def surface_points(depth: np.ndarray, mask: np.ndarray, intrinsics, c2w) -> np.ndarray:
    """(N, 3) world points of ``depth`` (H, W z-depth, metres) at ``mask`` pixels."""
    z = np.where(mask, depth, np.nan).astype(np.float32)
    cloud = depth_to_cloud(z, *intrinsics, c2w, normals=False, max_depth=1e4)
    return np.asarray(cloud.points)


def measure(run: Path) -> dict:
    model, info = load_model(run)
    _, ds = resolve_run_dataset(run, info["spec"].get("dataset"))
    centres, state_of = geom_centres(ds)
    step_times = np.load(ds.root / ds.manifest["capture"]["state_file"])["time"]
    flows = hasattr(model.field, "deformation") or hasattr(model.field, "move_points")
    ids = {name: int(k) for k, name in ds.manifest["geoms"].items()
           if name in ds.manifest["objects"]}
    tracked = {}  # object -> the body whose part tracks it alone
    if hasattr(model.field, "part_centres"):
        for body, geoms in (ds.manifest.get("moving_bodies") or {}).items():
            for name, g in ids.items():
                if geoms == [g]:
                    tracked[name] = body
    steps: dict[int, list[int]] = {}
    for i in ds.indices("test"):
        steps.setdefault(int(state_of[i]), []).append(i)
    kernel = np.ones((3, 3), np.uint8)
    rows = {name: [] for name in ids}
    for s, frames in sorted(steps.items()):
        field_pts = {name: [] for name in ids}
        true_pts = {name: [] for name in ids}
        for i in frames:
            img = render_image(model, ds.cameras([i]), 0, cond=[float(ds.times[i])],
                               supersample=1)
            for name, g in ids.items():
                mask = cv2.erode((ds.segmentations[i] == g).astype(np.uint8), kernel) > 0
                if not mask.any():
                    continue
                field_pts[name].append(surface_points(img["median_z_depth"], mask,
                                                    ds.intrinsics[i], ds.c2w[i]))
                true_pts[name].append(surface_points(ds.depths[i], mask, ds.intrinsics[i],
                                                   ds.c2w[i]))
        for name in ids:
            f = np.concatenate(field_pts[name]) if field_pts[name] else np.zeros((0, 3))
            t = np.concatenate(true_pts[name]) if true_pts[name] else np.zeros((0, 3))
            if not len(f) or not len(t):
                continue
            truth = centres[name][s]
            f_c, t_c = f.mean(0), t.mean(0)
            row = {"state": s, "time": float(ds.times[frames[0]]),
                   "views": len(field_pts[name]),
                   "field_cm": 100 * float(np.linalg.norm(f_c - truth)),
                   "depth_maps_cm": 100 * float(np.linalg.norm(t_c - truth)),
                   "field_vs_depth_maps_cm": 100 * float(np.linalg.norm(f_c - t_c))}
            if name in tracked:
                t_step = torch.tensor([float(ds.times[frames[0]])])
                track = model.field.part_centres(t_step)[tracked[name]][0].numpy()
                row["track_cm"] = 100 * float(np.linalg.norm(track - truth))
            if flows and s + 1 < len(step_times):
                moved = point_motion(model, torch.as_tensor(f, dtype=torch.float32),
                                     float(ds.times[frames[0]]), float(step_times[s + 1]))
                flow = (moved.points.numpy() - f).mean(0)
                true_motion = centres[name][s + 1] - truth
                row.update(flow_error_cm=100 * float(np.linalg.norm(flow - true_motion)),
                           true_motion_cm=100 * float(np.linalg.norm(true_motion)))
            rows[name].append(row)
    return {"run": str(run), "method": info["spec"]["method"], "objects": rows}


def summary(result: dict) -> list[str]:
    lines = []
    for name, rows in result["objects"].items():
        if not rows:
            continue
        cols = [np.array([r[k] for r in rows]) for k in
                ("field_cm", "depth_maps_cm", "field_vs_depth_maps_cm")]
        flow = [(r["flow_error_cm"], r["true_motion_cm"]) for r in rows if "flow_error_cm" in r]
        flow_text = (f"{np.median([a for a, _ in flow]):.2f} / {np.max([a for a, _ in flow]):.2f}"
                     f" (moved {np.median([b for _, b in flow]):.2f})") if flow else "–"
        track = [r["track_cm"] for r in rows if "track_cm" in r]
        track_text = f"{np.median(track):.2f} / {np.max(track):.2f}" if track else "–"
        lines.append(f"| {Path(result['run']).name} | {name} | {len(rows)} | "
                     + " | ".join(f"{np.median(c):.2f} / {c.max():.2f}" for c in cols)
                     + f" | {flow_text} | {track_text} |")
    return lines


def plot(results: list, path: Path) -> None:
    names = sorted({n for r in results for n in r["objects"]})
    fig = Figure(figsize=(3.2 * len(names), 3.0), constrained_layout=True)
    axes = fig.subplots(1, len(names), squeeze=False)[0]
    for ax, name in zip(axes, names):
        for k, r in enumerate(results):
            rows = r["objects"].get(name) or []
            t = [row["time"] for row in rows]
            ax.plot(t, [row["field_vs_depth_maps_cm"] for row in rows], "o-", color=f"C{k}",
                    label=Path(r["run"]).name)
            ax.plot(t, [row["field_cm"] for row in rows], ":", color=f"C{k}")
        ax.set_title(name)
        ax.set_xlabel("time")
        ax.set_ylabel("centre error, cm")
    axes[0].legend(fontsize=7, title="solid: field vs depth maps; dotted: vs MuJoCo",
                   title_fontsize=7)
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", type=Path, nargs="+")
    p.add_argument("--out", default="object_centres")
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    results = [measure(run) for run in args.runs]
    print("| run | object | steps | field vs MuJoCo, cm (median / max) | depth maps vs MuJoCo "
          "| field vs depth maps | scene flow to the next step vs MuJoCo | the part's track "
          "vs MuJoCo |")
    print("|---|---|---|---|---|---|---|---|")
    for r in results:
        print("\n".join(summary(r)))
    plot(results, HERE / f"{args.out}.png")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
