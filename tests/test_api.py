"""The scripting API: `napari_lbs._core.__all__` is curated, every name resolves, and docs/api.md documents exactly those names."""

import re
import subprocess
import sys
from pathlib import Path

import napari_lbs._core as core

API_DOC = Path(__file__).resolve().parents[1] / "docs" / "api.md"


def test_all_is_curated_and_every_name_resolves():
    assert 8 <= len(core.__all__) <= 60
    assert len(set(core.__all__)) == len(core.__all__)
    for name in core.__all__:
        assert not name.startswith("_")
        assert getattr(core, name) is not None


def test_api_page_documents_exactly_the_listed_names():
    documented = re.findall(r"^### `([A-Za-z_][A-Za-z0-9_]*)`$", API_DOC.read_text(), re.M)
    assert len(documented) == len(set(documented)), "a name documented twice in docs/api.md"
    assert sorted(documented) == sorted(core.__all__), (
        f"in __all__ but not in docs/api.md: {sorted(set(core.__all__) - set(documented))}; "
        f"in docs/api.md but not in __all__: {sorted(set(documented) - set(core.__all__))}"
    )


def test_every_public_name_is_used_by_an_example_of_its_section():
    """Each ``### name`` section's ``##`` chapter has an example that uses the name (more than importing it)."""
    unused = []
    for chapter in re.split(r"^## ", API_DOC.read_text(), flags=re.M)[1:]:
        code = "\n".join(re.findall(r"```python\n(.*?)```", chapter, re.S))
        body = re.sub(r"^from napari_lbs\._core import .*$", "", code, flags=re.M)
        unused += [name for name in re.findall(r"^### `([A-Za-z_][A-Za-z0-9_]*)`$", chapter, re.M) if not re.search(rf"\b{name}\b", body)]
    assert not unused, f"docs/api.md: no example of their chapter uses {unused}"


def test_results_and_settings_are_frozen():
    """The public results and settings refuse assignment; `dataclasses.replace` makes a changed copy."""
    import dataclasses

    frozen = ("PredictionResult", "PredictionSettings", "SequenceResult", "SimulatedSequence", "TrainingResult", "TrainingSettings", "LoadedModel",
              "SyntheticDataset", "RefineSettings", "SceneDiagnosisSettings", "CalibrationSettings", "CalibrationResult", "SceneDiagnosis", "ExperimentConfig", "ParticleField")
    for name in frozen:
        cls = getattr(core, name)
        assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen, f"{name} is not a frozen dataclass"
    result = core.PredictionResult({"x_um": []}, {}, 1.0)
    try:
        result.seconds = 2.0
    except dataclasses.FrozenInstanceError:
        pass
    else:
        raise AssertionError("PredictionResult accepted an assignment")
    assert dataclasses.replace(result, seconds=2.0).seconds == 2.0 and result.seconds == 1.0


def test_prediction_settings_and_keywords_give_the_same_table(detector, tiny_config):
    """`predict_particles` and `predict_sequence` take their options as one `PredictionSettings` or as keywords, not both."""
    import numpy as np
    import pytest

    frames = core.simulate_sequence(tiny_config, frames=2, flow="vortex", size=96, count=4, seed=1).frames
    settings = core.PredictionSettings(device="cpu", precision="float32", threshold=0.15)
    by_settings = core.predict_particles(frames[0], detector, settings=settings)
    by_keywords = core.predict_particles(frames[0], detector, device="cpu", precision="float32", threshold=0.15)
    assert by_settings.particles["x_um"].size and by_settings.provenance["threshold"] == 0.15
    for name, values in by_keywords.particles.items():
        np.testing.assert_array_equal(by_settings.particles[name], values)
    recording = core.predict_sequence(frames, detector, background="none", settings=settings)
    assert recording.provenance["threshold"] == 0.15 and recording.provenance["precision"] == "float32"
    np.testing.assert_array_equal(recording.particles["x_um"],
                                  core.predict_sequence(frames, detector, background="none", device="cpu", precision="float32", threshold=0.15).particles["x_um"])
    with pytest.raises(core.InputError, match="^threshold: give the prediction's options either in settings or as keywords"):
        core.predict_particles(frames[0], detector, settings=settings, threshold=0.3)
    with pytest.raises(core.InputError, match="^device, precision: give"):
        core.predict_sequence(frames, detector, settings=settings, device="cuda", precision="bfloat16")


def test_refined_prediction_is_the_predict_steps_refinement(monkeypatch, tmp_path, detector):
    """``napari-lbs predict --refine`` runs the public `refined_prediction` (network, fit, second look, material gate) and writes its table."""
    import numpy as np

    from napari_lbs._core import pipeline
    from napari_lbs._core.pipeline import _predict

    assert core.refined_prediction is pipeline.refined_prediction
    calls = []

    def refined(hologram, model, config, **options):
        calls.append(options)
        return core.PredictionResult({"x_um": np.array([1.0]), "y_um": np.array([2.0]), "z_um": np.array([2000.0]), "diameter_um": np.array([20.0])},
                                     {"model_sha256": "stub", "refine": {"detections": 1, "kept": 1, "seconds": 0.0, "residual": {"found": 0}}}, 0.1)

    monkeypatch.setattr(_predict, "refined_prediction", refined)
    request = pipeline.PredictRequest(np.ones((64, 64), np.float32), detector, tmp_path / "p.csv", device="cpu", threshold=0.15, material_index_contrast=0.26)
    pipeline.predict(request)
    assert calls[0]["settings"] == core.PredictionSettings(device="cpu", threshold=0.15) and calls[0]["material_index_contrast"] == 0.26
    assert core.read_particles(tmp_path / "p.csv")["z_um"].tolist() == [2000.0]


def test_api_page_examples_import_only_listed_names():
    for block in re.findall(r"```python\n(.*?)```", API_DOC.read_text(), re.S):
        for names in re.findall(r"^from napari_lbs\._core import (.+)$", block, re.M):
            unknown = {name.strip() for name in names.split(",")} - set(core.__all__)
            assert not unknown, f"docs/api.md imports private names {unknown}"


def test_private_names_are_not_handed_out():
    code = "import napari_lbs._core as c\ntry:\n    c.write_json\nexcept AttributeError:\n    pass\nelse:\n    raise SystemExit('write_json is public')\n"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_api_page_examples_run_in_order(tmp_path, monkeypatch):
    """Each section's example runs as it stands (the later ones use the files the earlier ones wrote)."""
    monkeypatch.chdir(tmp_path)
    for number, block in enumerate(re.findall(r"```python\n(.*?)```", API_DOC.read_text(), re.S)):
        exec(compile(block, f"docs/api.md example {number}", "exec"), {})
