"""Importing dva changes nothing in the process but Gymnasium's registry; dva.configure() sets what
runs need."""

from __future__ import annotations

import json
import subprocess
import sys

PROBE = r"""
import json, os, pkgutil, importlib
import jax, matplotlib, gymnasium
try:
    import warp
except ImportError:
    warp = None

def snapshot():
    return {
        "environ": dict(os.environ),
        "jax": {name: repr(value) for name, value in sorted(jax.config.values.items())},
        "matplotlib": matplotlib.rcParams._get_backend_or_none(),
        "warp": {} if warp is None else {
            k: repr(v) for k, v in vars(warp.config).items() if not k.startswith("_") and not callable(v)
        },
    }

before = snapshot()
import dva
modules = sorted(m.name for m in pkgutil.walk_packages(dva.__path__, "dva.") if not m.name.endswith("__main__"))
for name in modules:
    importlib.import_module(name)
after = snapshot()
from jax._src import xla_bridge
registered = sorted(env for env in gymnasium.registry if env.startswith("dva/"))
changed = {key: [k for k in set(before[key]) | set(after[key]) if before[key].get(k) != after[key].get(k)]
           if isinstance(before[key], dict) else before[key] != after[key] for key in before}
backends = bool(xla_bridge._backends)
dva.configure()
configured = {
    "xla_flags": os.environ.get("XLA_FLAGS", ""),
    "cache": jax.config.values["jax_compilation_cache_dir"],
}
print(json.dumps({"modules": len(modules), "changed": changed, "backends": backends,
                  "registered": registered, "configured": configured}))
"""


def test_importing_every_module_changes_nothing_but_the_gymnasium_registry():
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["modules"] > 40
    assert result["changed"] == {"environ": [], "jax": [], "matplotlib": False, "warp": []}
    assert not result["backends"], "an import started JAX's backends (XLA_FLAGS could no longer be set)"
    assert "dva/hopper-v0" in result["registered"]
    assert "xla_cpu_experimental_ynn_fusion_type" in result["configured"]["xla_flags"]
    assert result["configured"]["cache"]
