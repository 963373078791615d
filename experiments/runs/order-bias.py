"""Does the call measured right after OIDN (or another network) take longer than after a pause?

Run from the repository root: python experiments/runs/order-bias.py (docs/experiments.md)."""
import time, statistics, sys
sys.path.insert(0, '.')  # run from the repository root
from benchmarks.inference import _render, call
from denoise import Denoiser
from denoise.oidn import oidn_denoise
img, var = _render(1280, 720)
fast = Denoiser('fast'); high = Denoiser('high')
f = lambda: call(fast, img, var, 4)
o = lambda: oidn_denoise(img)
h = lambda: call(high, img, var, 16)
for fn in (f, o, h): fn()
res = {k: [] for k in ('after_oidn', 'after_pause', 'after_net', 'oidn_after_net', 'oidn_after_pause')}
for r in range(5):
    o(); t = time.perf_counter(); f(); res['after_oidn'].append(time.perf_counter() - t)
    time.sleep(1.0); t = time.perf_counter(); f(); res['after_pause'].append(time.perf_counter() - t)
    h(); t = time.perf_counter(); f(); res['after_net'].append(time.perf_counter() - t)
    h(); t = time.perf_counter(); o(); res['oidn_after_net'].append(time.perf_counter() - t)
    time.sleep(1.0); t = time.perf_counter(); o(); res['oidn_after_pause'].append(time.perf_counter() - t)
for k, v in res.items():
    print(k, round(statistics.median(v), 3), [round(x, 3) for x in v])
