"""A spectrum's width as a model of the frame: each depth group's fringes washed out as exp(−½(π σ_λ z f²)²), against a sensor's blur and a source's size.

Each frame is diagnosed (`diagnose_scene`), the scene its selection starts from is kept,
and on it the baseline, a sensor's blur, a source's size and a spectrum's width (coherence
fitted as ``bandwidth_nm``: each depth group's hologram less 1 filtered by
``exp(−½ (π σ_λ z f²)²)``, `Scene.spectral_blur`) are each fitted on one colour of the
checkerboard and judged on the other (`fit_frame`, the engine's held-out Whittle
likelihood), whatever the selection would name: the comparison `spectrum_width_test` makes
in a named blur's place, for every blur. Printed per frame: each model's summed gain over the baseline and its sign
test's z, its fitted parameter, and the spectrum's width against the sensor's blur.

    python benchmarks/withheld_suite.py make development /tmp/dev
    python benchmarks/bench_bandwidth_model.py /tmp/dev/led-bandwidth.tif /tmp/dev/crosstalk.tif /tmp/dev/source-disc.tif /tmp/dev/control-1.tif
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np

import napari_lbs._core.gap._nested as nested
import napari_lbs._core.gap._scene_diagnosis as scene_diagnosis
from napari_lbs._core import load_config, read_hologram
from napari_lbs._core.foundation import available_threads
from napari_lbs._core.gap import SceneDiagnosisSettings, diagnose_scene
from napari_lbs._core.gap._heldout import TileSplit
from napari_lbs._core.gap._nested import fit_frame
from napari_lbs._core.gap._scene_image import Scene
from napari_lbs._core.refine import RefineSettings

def _scene_of(image: np.ndarray, workers: int) -> tuple[np.ndarray, Scene]:
    """The frame as the diagnosis divides it and the scene its selection starts from."""
    kept = {}
    select = scene_diagnosis.select_effects

    def keeping(data, scene, split, **options):
        kept.setdefault("scene", (data, scene))
        return select(data, scene, split, **options)

    scene_diagnosis.select_effects = keeping
    try:
        diagnose_scene(image, load_config(), settings=SceneDiagnosisSettings(refine=RefineSettings(min_gain=0.0, workers=workers)))
    finally:
        scene_diagnosis.select_effects = select
    return kept["scene"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("frames", nargs="+", type=Path)
    parser.add_argument("--workers", type=int, default=available_threads())
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    load_before = os.getloadavg()[0]
    rows = []
    for path in args.frames:
        data, scene = _scene_of(read_hologram(path), args.workers)
        split = TileSplit.of(data.shape)
        fits = {"baseline": fit_frame(data, scene, split, ()), "sensor_blur": fit_frame(data, scene, split, ("sensor_blur",)),
                "source_size": fit_frame(data, scene, split, ("coherence",)),
                "spectrum_width": fit_frame(data, scene, split, ("coherence",), parameters={"coherence": ("bandwidth_nm",)})}
        row = {"frame": path.name}
        for name in ("sensor_blur", "source_size", "spectrum_width"):
            gain, z = nested.gain_and_z(fits[name].loglik, fits["baseline"].loglik)
            row[name] = {"gain_nats": round(gain, 1), "z": round(z, 2), "params": {k: round(v, 4) for k, v in fits[name].params[0].items() if "." in k}}
        gain, z = nested.gain_and_z(fits["spectrum_width"].loglik, fits["sensor_blur"].loglik)
        row["spectrum_over_sensor"] = {"gain_nats": round(gain, 1), "z": round(z, 2)}
        print(json.dumps(row), flush=True)
        rows.append(row)
    result = {"frames": rows, "load_average": [load_before, os.getloadavg()[0]]}
    if args.out:
        args.out.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
