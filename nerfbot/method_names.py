"""The methods' names and one-line descriptions, for the command line.

The ``nerfbot`` parser lists and checks method names from here, without importing the
registry (:mod:`nerfbot.methods` imports every field, torch and numba), so ``nerfbot --help``
stays fast. ``tests/test_registry.py`` checks that this table and the registry list the same
methods and the same baked ones.
"""

from __future__ import annotations

#: Method name -> one line for ``nerfbot train --help``, in the registry's order.
DESCRIPTIONS = {
    "ngp": "Instant-NGP hash grid + occupancy-grid marching (fast default)",
    "plenoxels": "Plenoxels: sparse voxel grid of density + SH colour, no network, "
                 "coarse-to-fine with pruning",
    "nerf": "vanilla NeRF, positional encoding, coarse + fine (reference)",
    "mipnerf": "mip-NeRF: cones, integrated positional encoding, one MLP for coarse + fine "
               "(anti-aliased at lower resolutions)",
    "tensorf": "TensoRF: vector-matrix factorised grids, coarse-to-fine upsampling + "
               "occupancy-grid marching",
    "tnerf": "T-NeRF: time or joints as an extra input of an NGP field",
    "dnerf": "D-NeRF: deformation (space-time planes) into a canonical NGP field",
    "kplanes": "static NGP field + K-Planes space-time planes for what moves (densities "
               "added)",
    "rigid": "kplanes + one small field per moving rigid body, carried along a track of poses "
             "that starts from the segmentation and trains",
    "articulated": "one NGP field per rigid part, placed by forward kinematics of the joints",
    "plenoctree": "PlenOctrees' NeRF-SH: hash grid -> density + SH colour (no direction "
                  "input); bake with `nerfbot bake --octree`",
    "plenoctree_octree": "a baked PlenOctree (made by `nerfbot bake --octree` from a "
                         "plenoctree run; not trained from scratch)",
    "fastnerf": "FastNeRF: position net (hash grid) x direction net, colour = sigmoid(sum_i "
                "beta_i(d) u_i(x)); cacheable with `nerfbot bake --cache`",
    "kilonerf": "KiloNeRF: a 16^3 grid of tiny MLPs, distilled from a trained run (option "
                "teacher_run) then fine-tuned",
    "fastnerf_cache": "baked FastNeRF cache (made by `nerfbot bake --cache NP,ND`; not "
                      "trainable)",
}

#: Baked method -> the method whose trained runs it is baked from (``nerfbot bake --method``).
BAKED = {"plenoctree_octree": "plenoctree", "fastnerf_cache": "fastnerf"}
