"""Where a trained run's render time goes: cProfile of 100 ``render_image`` calls over the
test views (the numba kernels show as single entries). usage: profile_render.py DATA RUN"""
import cProfile
import pstats
import sys

from nerfbot.data import load_dataset
from nerfbot.query.render import render_image
from nerfbot.train.runs import load_model

if len(sys.argv) != 3:
    sys.exit(__doc__)
ds = load_dataset(sys.argv[1])
cams = ds.cameras(ds.indices("test"))
model = load_model(sys.argv[2])[0].eval()
render_image(model, cams, 0)  # compile / warm caches
profile = cProfile.Profile()
profile.enable()
for k in range(100):
    render_image(model, cams, k % len(cams))
profile.disable()
pstats.Stats(profile).sort_stats("tottime").print_stats(25)
