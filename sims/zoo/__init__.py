"""The scene zoo: generated scene families that vary with a seed, one module each.

``workspace`` (a frame-filling textured work table with labelled boxes, cans and tools seen from
close by), ``room`` (a closed room with furniture and a narrow passage, seen from cameras inside
it: the ``inside`` rig; ``room_glass`` is the same room with a glass partition), ``bins``
(small parts in a tray, seen from 0.3-0.6 m) and ``yard`` (an unbounded outdoor scene: objects
near the cameras, buildings and hills 20-100 m away, sky); ``tossed`` (props thrown onto a
table, sometimes beside a pendulum: a dynamic scene, captured over time). Each
family is a function ``seed -> GeneratedScene`` (MJCF text plus procedural PNG textures from
:mod:`sims.zoo.textures`), registered in :func:`sims.scene._generators`, so ``room:3`` names a
scene everywhere a scene name is accepted; the same seed always gives the same bytes, and the
seed changes layout, textures and lighting. Units are metres and degrees, z up.
"""
