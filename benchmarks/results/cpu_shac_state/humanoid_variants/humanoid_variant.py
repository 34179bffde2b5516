"""Humanoid model variants, measured in benchmarks/RESULTS.md ("Humanoid: SHAC's motor strength and contacts") (SHAC's reference humanoid vs ours) for gradient and training checks.
usage: python humanoid_variant.py VARIANT grad|train MINUTES RUN_DIR [STATE_GRAD_CLIP]
VARIANT: ours | motors (gears x1.75 = SHAC's 0.35 x strengths) | contacts (kd 5e3, mu 0.75) | both"""
import sys
import dva.tasks.legged as L
from dva.tasks.physics import PenaltyContact

variant, what = sys.argv[1], sys.argv[2]
if variant in ("motors", "both"):
    original = L.Humanoid.build_spec
    def build_spec(self):
        spec = original(self)
        for actuator in spec.actuators:
            gear = list(actuator.gear); gear[0] *= 1.75; actuator.gear = gear
        return spec
    L.Humanoid.build_spec = build_spec
if variant in ("contacts", "both"):
    L.Humanoid.penalty_contact = PenaltyContact(ke=2e4, kd=5e3, kf=1e3, mu=0.75)

if what == "grad":
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[3]))  # benchmarks/
    from gradients import gradient_norms, HORIZONS
    from dva.tasks import make_task
    print("gears", make_task("humanoid").mj_model.actuator_gear[:6, 0])
    norms = gradient_norms("humanoid", "penalty", 16).mean(axis=1)
    print(variant, " ".join(f"{n:.3g}" for n in norms), "ratio", f"{norms[-1]/norms[0]:.3g}", "h32/h16", f"{norms[-1]/norms[-2]:.2g}", flush=True)
else:
    from pathlib import Path
    from dva.training import train
    clip = float(sys.argv[5]) if len(sys.argv) > 5 else None
    train("humanoid", "shac", preset="cpu", minutes=float(sys.argv[3]), run_dir=Path(sys.argv[4]), eval_every=100, state_grad_clip=clip)
