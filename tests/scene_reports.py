"""A stand-in for `diagnose_scene`: the report's every field, phases, progress and stops, in milliseconds.

For the tests of what runs around the diagnosis (the pooling of frames, the widget, the
workflow dock); the diagnosis itself is run for real in tests/test_diagnosis.py and
tests/test_nested_effects.py.
"""

from __future__ import annotations

import numpy as np

from napari_lbs._core import Stopped

_MEAN = {"illumination": {"depth": 0.3, "x0": 0.1, "y0": -0.1}, "sensor_blur": {"sigma_px": 0.8}, "parasitic_fringes": {"amplitude": 0.02, "period_px": 12.0, "angle_rad": 0.5},
         "coherence": {"theta_mrad": 0.4}}


def scene_report(verdict: str | None = None, *, explains: bool = True, params: dict | None = None, grid: int = 2, tile_px: int = 128) -> dict:
    """A report as `diagnose_scene` gives it, naming ``verdict`` (effects joined by "+"); ``params`` replace an effect's own."""
    named = set((verdict or "").split("+")) - {""}
    params = params or {}
    # errors 0.01 where the frame names the effect, 0.5 where it does not: pooled reports must keep each effect's own
    effects = [{"id": effect, "gap_after": 0.02, "shrink": 0.5, "params": params.get(effect, values),
                "params_err": dict.fromkeys(params.get(effect, values), 0.01 if effect in named else 0.5), "heldout_gain_nats": 40.0 if effect in named else -3.0,
                "z": 6.0 if effect in named else -1.0, "selected": effect in named} for effect, values in _MEAN.items()]
    effects += [
        {"id": "particle_phase", "gap_after": 0.04, "shrink": 0.0, "z": 0.5, "selected": "particle_phase" in named,
         "params": params.get("particle_phase", {"index_contrast": 0.26, "transmission": 1.0} if "particle_phase" in named else {})},
        {"id": "shot_noise", "gap_after": 0.04, "shrink": 0.0, "z": 0.2, "heldout_gain_nats": 1.0, "selected": "shot_noise" in named, "params": {"log10_photons": 3.0}},
        {"id": "quantization", "gap_after": 0.04, "shrink": 0.0, "z": None, "selected": "quantization" in named,
         "params": params.get("quantization", {"bits": 6.0, "saturation": 1.6} if "quantization" in named else {}),
         "levels": {"integer": True, "step_counts": 4, "noise_share": 0.5, "saturated_share": 0.0, "saturation_noise_share": 0.0}},
    ]
    effects.sort(key=lambda e: -(e["z"] if e["z"] is not None else -np.inf))
    bands = [{"cycles_per_px": [low, high], "share_of_power": 0.1, "structured": 0.05} for low, high in ((0.0, 0.1), (0.1, 0.35), (0.35, 0.5))]
    residual = 0.03 if explains else 0.2
    return {
        "method": "scene",
        "gap": {"metric": "unexplained share of the frame's structure (median over the held-out tiles)", "baseline": 0.04, "by_band": bands,
                "line_pattern": {"columns": 1.0, "rows": 1.1}, "particles": 4, "tiles": grid * grid, "tile_px": tile_px},
        "effects": effects,
        "verdict": {"id": verdict, "shrink": 1.0 - residual / 0.04, "residual": residual, "undecided": [], "catalog_explains": explains, "probability": 0.9,
                    "reason": f"selected by held-out gain (z >= 3): {', '.join(sorted(named)) or 'nothing'}"},
        "posterior": {"null": 0.1, **{effect: 0.9 / len(_MEAN) for effect in _MEAN}},
        "confidence": [{"name": f"{effect} kept", "outcome": 1, "holds": 0.9} for effect in sorted(named)],
        "particle_optics": {"particles": 4, "model": "undecided", "z": 0.5, "index_contrast": 0.26, "camera_blur_px": 0.0, "diameter_median_um": 25.0,
                            "diameter_quartiles_um": [24.0, 26.0],
                            "power_spectrum": {"model": "undecided", "z": 0.5, "transparent_better": 9, "transparent_worse": 7, "index_contrast": 0.26,
                                               "heldout_error": {"opaque": 1e-7, "0.26": 1e-7}, "slope": {"opaque": 0.9, "0.26": 0.5},
                                               "band_cycles_per_px": [0.08, 0.7]},
                            "through_focus": {"model": "undecided", "z": 0.0, "transparent_better": 2, "transparent_worse": 2, "spheres": 4,
                                              "index_contrast": 0.26, "profile_distance": {"opaque": 0.1, "0.26": 0.1}, "relative_depths": [-8.0, 4.0]}},
        "selection": [],
        "not_tested": {"spherical_wave": "not on one frame", "multiple_scattering": "not modelled"},
    }


class StandIn:
    """Called as `diagnose_scene`: names two phases, counts their steps, stops when asked; each call's report names the next of ``verdicts``.

    ``verdicts`` are ``(verdict, catalog_explains)`` or ``(verdict, catalog_explains, params)``,
    one per call, the last repeated. ``calls`` records each call's frame, settings and pool;
    ``wait_for_stop``: the second phase runs until ``should_stop`` says stop.
    """

    def __init__(self, verdicts=((None, True),), *, wait_for_stop: bool = False) -> None:
        self.verdicts, self.wait_for_stop, self.calls = list(verdicts), wait_for_stop, []

    def __call__(self, hologram, config, *, settings=None, background=None, progress=None, should_stop=None, pool=None):
        import time

        from napari_lbs._core.gap import SceneDiagnosis, SceneDiagnosisSettings

        settings = settings or SceneDiagnosisSettings()
        self.calls.append({"hologram": np.asarray(hologram), "settings": settings, "background": background, "pool": pool})
        verdict, explains, *params = self.verdicts[min(len(self.calls), len(self.verdicts)) - 1]
        for name in ("particles found", "the catalog's effects"):
            if progress is not None and hasattr(progress, "phase"):
                progress.phase(name)
            for step in range(1, 3):
                while self.wait_for_stop and name != "particles found" and not (should_stop and should_stop()):
                    time.sleep(0.02)
                if should_stop is not None and should_stop():
                    raise Stopped()
                if progress is not None:
                    progress(step, 2)
        size = min(np.shape(hologram)[:2]) // settings.grid
        report = scene_report(verdict, explains=explains, params=params[0] if params else None, grid=settings.grid, tile_px=size)
        tile_map = np.linspace(0.0, 0.2, settings.grid**2).reshape(settings.grid, settings.grid)
        return SceneDiagnosis(report, tile_map, None, 0.01)
