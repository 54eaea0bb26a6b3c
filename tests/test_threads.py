import json
import os
import subprocess
import sys

import pytest

# A fresh process, sized before its libraries load (the console script) or after (a script);
# it reports what each library got.
_PROBE = """
import json, sys
from napari_lbs._core.foundation._threads import process_threads, size_threads, thread_pool
SIZING
from threadpoolctl import threadpool_info
from napari_lbs._core import backpropagate
backpropagate(numpy.ones((32, 32), numpy.float32), [1000.0], wavelength_um=0.66, pixel_um=2.2)
blas = sorted({pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"})
print(json.dumps({"count": process_threads(), "torch": torch.get_num_threads(), "blas": blas, "pool": thread_pool("asm")._max_workers}))
"""


def _probe(sizing: str, *, cores: set[int] | None = None, env: str | None = None) -> dict:
    environ = {key: value for key, value in os.environ.items() if key not in ("NAPARI_LBS_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    if env is not None:
        environ["NAPARI_LBS_THREADS"] = env
    result = subprocess.run([sys.executable, "-c", _PROBE.replace("SIZING", sizing)], capture_output=True, text=True, env=environ,
                            preexec_fn=(lambda: os.sched_setaffinity(0, cores)) if cores else None)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="needs CPU affinity (Linux)")
@pytest.mark.parametrize("sizing", ["size_threads()\nimport numpy, torch", "import numpy, torch\nsize_threads()"], ids=["before-import", "after-import"])
def test_threads_follow_the_cores_the_process_may_run_on_and_the_override(sizing):
    cores = sorted(os.sched_getaffinity(0))
    everywhere = lambda n: {"count": n, "torch": n, "blas": [n], "pool": n}
    assert _probe(sizing) == everywhere(len(cores))
    assert _probe(sizing, cores={cores[0]}) == everywhere(1)  # taskset -c 0
    assert _probe(sizing, env="1") == everywhere(1)
    if len(cores) > 2:
        assert _probe(sizing, env="2") == everywhere(2)


def test_a_bad_override_is_one_line_naming_the_variable(tmp_path):
    environ = dict(os.environ, NAPARI_LBS_THREADS="two")
    result = subprocess.run([sys.executable, "-m", "napari_lbs._cli", "config", "--write", str(tmp_path / "c.toml")], capture_output=True, text=True, env=environ)
    assert result.returncode == 2 and "NAPARI_LBS_THREADS" in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "c.toml").exists()


_WAITING = """
import json, os
from napari_lbs._core.foundation._threads import size_threads
size_threads()
print(json.dumps({name: os.environ.get(name) for name in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}))
"""


@pytest.mark.parametrize(("given", "expected"), [({}, {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": "1000"}),
                                                 ({"OMP_WAIT_POLICY": "ACTIVE"}, {"OMP_WAIT_POLICY": "ACTIVE", "GOMP_SPINCOUNT": None}),
                                                 ({"GOMP_SPINCOUNT": "0"}, {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": "0"})],
                         ids=["default", "the-users-policy", "the-users-spin"])
def test_openmp_threads_wait_by_a_short_spin_then_sleep_unless_the_user_says_otherwise(given, expected):
    environ = {key: value for key, value in os.environ.items() if key not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    result = subprocess.run([sys.executable, "-c", _WAITING], capture_output=True, text=True, env={**environ, **given})
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout.strip().splitlines()[-1]) == expected
