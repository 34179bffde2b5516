"""Why a DreamerV3 Cart-pole balance policy scores what it does: replays a run's latest checkpoint
(one episode per env) and prints when the cart leaves the rail and when the pole falls (|θ| > 0.5).

    python benchmarks/results/dreamerv3_balance/failure_mode.py RUN_DIR
"""
import sys, numpy as np
from dva.training import evaluate_run
from dva.tasks import make_task
spec, returns, qpos, _ = evaluate_run(sys.argv[1])
limit = make_task("cartpole_balance").cart_limit
x, th = qpos[..., 0], np.arctan2(np.sin(qpos[..., 1]), np.cos(qpos[..., 1]))
print("returns", np.round(returns))
for n in range(x.shape[1]):
    off = np.nonzero(np.abs(x[:, n]) >= limit)[0]
    fell = np.nonzero(np.abs(th[:, n]) > 0.5)[0]
    print(f"env {n}: off rail at {off[0] if len(off) else '-'}, |θ|>0.5 at {fell[0] if len(fell) else '-'}, "
          f"x at 30/60/90/119: {x[[30,60,90,119], n].round(2)}, θ: {th[[30,60,90,119], n].round(2)}")
