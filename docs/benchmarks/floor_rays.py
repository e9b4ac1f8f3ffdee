"""Which training rays ``--option floor_background`` acts on: those crossing top to bottom.

usage: python docs/benchmarks/floor_rays.py DATASET [DATASET ...]

For the centre rays of 20000 training pixels spread evenly over each dataset's training views
(the bounds from its manifest or cameras, as ``nerfbot train`` takes them), prints the share
that leaves the bounds through their bottom face and the share that crosses them from the top
face to the bottom face (the rays the option acts on).
"""

from __future__ import annotations

import argparse

import torch

from nerfbot.data import load_dataset
from nerfbot.data.pixels import PixelBank
from nerfbot.ops.sampling import ray_aabb


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", nargs="+")
    args = ap.parse_args()
    print("| dataset | rays leaving through the bottom face | crossing from top to bottom |")
    print("|---|---|---|")
    for path in args.datasets:
        ds = load_dataset(path)
        bank = PixelBank(ds, ds.indices("train"), torch.device("cpu"), None)
        rays = bank.centre_rays(torch.linspace(0, len(bank) - 1, 20000).long())
        box = torch.as_tensor(ds.aabb, dtype=torch.float32)
        t_near, t_far, hit = ray_aabb(rays.origins, rays.directions, box)
        exit_z = rays.origins[:, 2] + rays.directions[:, 2] * t_far
        bottom = hit & (rays.directions[:, 2] < 0) & ((exit_z - box[0, 2]).abs() < 1e-4)
        crossing = bank.top_to_bottom_share(box, 20000)   # what floor_background=auto reads
        print(f"| {path} | {100 * float(bottom.float().mean()):.1f} % | {100 * crossing:.1f} % |")


if __name__ == "__main__":
    main()
