"""The toy rollout the dynamic fields' tests train on: a cube and a ball sliding across a floor
at 0.6 m/s (no gravity), captured by 8 fixed cameras at 48 x 48 over 12 time steps, every 4th
held out."""

from __future__ import annotations

from pathlib import Path

TOY_MOVERS = """
    <body name="cube" pos="-0.3 -0.15 0.12">
      <joint name="cube_slide" type="slide" axis="1 0 0" damping="0"/>
      <geom name="cube" type="box" size="0.09 0.09 0.09" material="red" contype="0"
            conaffinity="0"/>
    </body>
    <body name="ball" pos="0.2 -0.3 0.12">
      <joint name="ball_slide" type="slide" axis="0 1 0" damping="0"/>
      <geom name="ball" type="sphere" size="0.08" material="blue" contype="0" conaffinity="0"/>
    </body>
"""
TOY_ROLLOUT = dict(
    custom="""<text name="nerfbot_capture" data="dynamic"/>
    <numeric name="nerfbot_duration" data="1.0"/>
    <text name="nerfbot_objects" data="cube ball"/>""",
    options='<option gravity="0 0 0"/>',
    extra='<keyframe><key name="init" qpos="0 0" qvel="0.6 0.6"/></keyframe>')


def capture_toy_rollout(folder: Path, toy_mjcf) -> Path:
    """Write the toy scene into ``folder`` and capture it; returns the dataset folder.
    ``toy_mjcf``: the conftest fixture of that name."""
    from sims.dynamic import capture_dynamic
    from sims.sequence import sequence_rig

    scene = folder / "toy.xml"
    scene.write_text(toy_mjcf("toy_rollout", TOY_MOVERS, **TOY_ROLLOUT))
    rig = sequence_rig(scene, "multiview", 8, size=48, radius=1.8)
    return capture_dynamic(scene, rig, folder / "data", frames=12, test_every=4, progress=False)
