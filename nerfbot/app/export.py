"""``nerfbot export RUN pointcloud|mesh|tsdf --out FILE``: a trained run's geometry as files.

Point clouds (.ply / .pcd / .xyz) and meshes (.ply / .obj / .glb), in the dataset's world frame
and metres (:mod:`nerfbot.query.geometry`). The depth behind point clouds and TSDF meshes is
the run's default query (threshold depth for scenes with glass, from ``RUN/auto.json``) unless
``--depth-mode`` says otherwise; the marching-cubes mesh cuts the density at that query's
threshold when it has one, at ``--threshold`` when given, else at the default surface density.
"""

from __future__ import annotations

from pathlib import Path

from nerfbot.app.cli import UsageError, _render_dataset, _render_depth_query

#: What ``nerfbot export`` writes: kind -> the file suffixes it accepts.
EXPORT_KINDS = {"pointcloud": (".ply", ".pcd", ".xyz"), "mesh": (".ply", ".obj", ".glb"),
                "tsdf": (".ply", ".obj", ".glb")}


def _bounds(args, model):
    """(2, 3) export box: ``--aabb``, else the run's bounds."""
    import numpy as np

    if args.aabb is None:
        return model.aabb.detach().cpu().numpy().astype(float)
    box = np.asarray(args.aabb, float).reshape(2, 3)
    if not np.all(box[1] > box[0]):
        raise UsageError(f"--aabb: every max must exceed its min, got {args.aabb}")
    return box


def _condition(args, info):
    """The one condition vector the export shows (None for a static run)."""
    from nerfbot.data.conditioning import Conditioning

    conditioning = Conditioning.from_dict(info["spec"].get("conditioning"))
    for flag, given, kind in (("--time", args.time is not None, "time"),
                              ("--joints", bool(args.joints), "joints")):
        if given and conditioning.kind != kind:
            raise UsageError(f"{flag}: {args.run} is a {conditioning.kind} run, not conditioned "
                             f"on {kind}")
    if conditioning.kind == "time" and args.time is None:
        raise UsageError(f"{args.run} is time-conditioned: give --time T (one state is exported)")
    return conditioning.vector(args.time, args.joints)


def cmd_export(args) -> int:
    from nerfbot.data.outputs import check_output_file
    from nerfbot.query.density import default_density_threshold
    from nerfbot.query.geometry import (DepthQuery, density_mesh, point_cloud, tsdf_mesh,
                                        write_mesh, write_point_cloud)
    from nerfbot.train.runs import load_model

    run, out = Path(args.run), Path(args.out)
    suffixes = EXPORT_KINDS[args.kind]
    if out.suffix.lower() not in suffixes:
        raise UsageError(f"--out {out}: a {args.kind} is written as {', '.join(suffixes)}")
    check_output_file(out, overwrite=args.overwrite)
    if not out.parent.is_dir():
        raise UsageError(f"--out {out}: folder {out.parent} does not exist")
    mode, threshold, source = _render_depth_query(args, run)
    model, info = load_model(run, args.device)
    cond = _condition(args, info)
    bounds = _bounds(args, model)
    progress = not args.no_progress
    if args.kind == "mesh":
        level = args.threshold if args.threshold is not None else threshold
        if level is None:
            level = default_density_threshold(model.aabb.detach().cpu().numpy())
        mesh = density_mesh(model, threshold=level, resolution=args.resolution, bounds=bounds,
                            cond=cond)
        if not len(mesh.faces):
            raise ValueError(f"{run}: no density reaches {level:g} /m inside the box: no surface "
                             "to write; give a lower --threshold")
        write_mesh(mesh, out)
        what = f"{len(mesh.vertices)} vertices, {len(mesh.faces)} faces, marching cubes at " \
            f"{level:g} /m"
    else:
        query = DepthQuery(mode, threshold)
        ds = _render_dataset(args, run, info, needed=True)
        idx = ds.indices(args.views) if args.views != "all" else list(range(len(ds)))
        if not idx:
            raise UsageError(f"--views {args.views}: the dataset has no such views")
        cams = ds.cameras(idx)
        conds = None if cond is None else [cond] * len(cams)
        nothing = (f"{run}: no rendered depth ({query.describe()}) inside the box at the "
                   f"{len(cams)} {args.views} views: nothing to write")
        if args.kind == "pointcloud":
            cloud = point_cloud(model, cams, query, conds, bounds=bounds, stride=args.stride,
                                voxel=args.voxel, progress=progress)
            if not len(cloud.points):
                raise ValueError(nothing)
            write_point_cloud(cloud, out)
            what = f"{len(cloud.points)} points"
        else:
            mesh = tsdf_mesh(model, cams, query, conds, voxel=args.voxel, bounds=bounds,
                             progress=progress)
            if not len(mesh.faces):
                raise ValueError(nothing)
            write_mesh(mesh, out)
            what = f"{len(mesh.vertices)} vertices, {len(mesh.faces)} faces, TSDF"
        what += f" from {len(cams)} {args.views} views, depth: {query.describe()} ({source})"
    print(f"wrote {out}: {what}; world frame, metres")
    return 0


def add_export_parser(sub, positive_int, positive_float, device, unit_time, joint_values) -> None:
    """The ``export`` subcommand's arguments (the argument types come from the CLI module)."""
    p = sub.add_parser("export", help="a run's geometry as files: point cloud, mesh or TSDF "
                                      "mesh, in world metres")
    p.add_argument("run", type=Path)
    p.add_argument("kind", choices=tuple(EXPORT_KINDS),
                   help="pointcloud: rendered depth back-projected; mesh: marching cubes on "
                        "density; tsdf: rendered depth fused in a TSDF and meshed")
    p.add_argument("--out", required=True, type=Path,
                   help="file: .ply/.pcd/.xyz (pointcloud) or .ply/.obj/.glb (mesh, tsdf)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing file")
    p.add_argument("--views", default="train", choices=("train", "test", "all"),
                   help="cameras whose rendered depth makes a pointcloud or tsdf (default train)")
    p.add_argument("--aabb", type=float, nargs=6, default=None,
                   metavar=("XMIN", "YMIN", "ZMIN", "XMAX", "YMAX", "ZMAX"),
                   help="crop to this box, metres (default: the run's bounds)")
    p.add_argument("--resolution", type=positive_int, default=256,
                   help="mesh: marching-cubes cells along the box's longest side (default 256)")
    p.add_argument("--voxel", type=positive_float, default=None, metavar="M",
                   help="tsdf: voxel size in metres (default: the box's longest side / 256); "
                        "pointcloud: merge points within voxels of this size (default: keep all)")
    p.add_argument("--stride", type=positive_int, default=1,
                   help="pointcloud: every N-th pixel per axis")
    p.add_argument("--depth-mode", default=None, choices=("expected", "median", "threshold"),
                   help="depth of pointcloud and tsdf: default the run's auto.json query "
                        "default (threshold for glass), else expected")
    p.add_argument("--threshold", type=float, default=None, metavar="M",
                   help="density threshold, 1/m: of --depth-mode threshold, and the surface of "
                        "a mesh")
    p.add_argument("--data", type=Path, default=None,
                   help="dataset whose cameras to render (default: the run's)")
    p.add_argument("--device", type=device, default="cpu")
    p.add_argument("--no-progress", action="store_true")
    cond = p.add_argument_group("dynamic and articulated runs (one state is exported)")
    cond.add_argument("--time", type=unit_time, default=None, metavar="T",
                      help="export the scene at time T in [0, 1]")
    cond.add_argument("--joints", type=joint_values, default=None, metavar="NAME=V,...",
                      help="export at these joint positions (others at the middle of their range)")
    p.set_defaults(func=lambda args: cmd_export(args))
