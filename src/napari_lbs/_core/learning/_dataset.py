"""Better synthetic training data: random groups through HCS and Holo-processing, on disk.

A *group* is one random particle field in a ``tile.size`` window, its simulated hologram
(with any effects of the catalog added, `effect_hologram`) turned into input planes by
Holo-processing with the calibrated parameters, the label planes
of the seed's formulation (3x3 squares of value 4 x diameter, `label_planes`) and the ground
truth. Two layouts (`DatasetLayout`):

``stack`` (default, for the ``focus`` formulation)
    the input planes are the reconstruction grid of the config (``z_min_um`` … ``z_max_um``
    every ``z_step_um``) extended by ``context_planes`` on each side, so that a network can
    see the planes around any depth of the volume; particles at continuous depths (or on the
    seed's layers, ``depths="layers"``). Inputs are stored as float16 (they lie in [0, 1]).
``layers`` (the seed's data, Sec. 2.1)
    12 particles on layers 1800–4800 µm every ``layer_step_um``, one input plane per layer.

The data set folder (documented in docs/dataset.md)::

    DATA/dataset.json            what the set is: format, config, processing, layout, effects, seed, planes, groups
    DATA/groups/group_00000.tif  series 0: input planes (z, y, x) float32 or float16
                                 series 1: label planes (z, y, x) float32 (zlib)
                                 ImageDescription JSON of page 0: group, seed, z_um, particles

Every group is drawn from the seed ``[seed, group]`` alone, so a set is the same whatever
order, interruptions or resumptions produced it; each group file is written atomically and
a rerun with the same settings only writes the groups that are missing.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from napari_lbs import __version__
from napari_lbs._core.calibration import HoloParams, holo_processing
from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.physics import check_effects, effect_hologram
from napari_lbs._core.foundation import atomic_path, read_json_object, write_json
from napari_lbs._core.foundation import InputError
from napari_lbs._core.foundation import ProgressCallback, Steps, StopCallback, Stopped, run_in_workers
from napari_lbs._core.physics import Distractors, ParticleField, SizeDistribution, distractor_scene, label_planes, random_particle_field, simulate_hologram
from napari_lbs._core.foundation import check_dataset_manifest

__all__ = ["DatasetLayout", "InputProcessing", "SyntheticDataset", "synthetic_group", "generate_dataset", "open_dataset", "dataset_summary", "DATASET_FORMAT"]

DATASET_FORMAT = "napari-lbs-dataset"
_FORMAT_VERSION = 2  # 2 added the layout; version 1 sets are the layers layout


@dataclass(frozen=True)
class InputProcessing:
    """How network inputs are made, for synthetic training planes and for real planes alike.

    Attributes
    ----------
    params : HoloParams
        Holo-processing of synthetic holograms; (0, 0, 1) is the seed's "normal simulation".
    invert_experiment : bool
        Whether real reconstruction planes are inverted (``1 - I``) before the network. The
        calibration fits synthetic planes to *inverted* experimental ones (``I_e``), so a
        calibrated set inverts; an uncalibrated one does not.
    mode : {"robust", "seed"}
        Per-plane normalisation: float (robust) or the seed's 8-bit stretch.
    """

    params: HoloParams = field(default_factory=HoloParams)
    invert_experiment: bool = False
    mode: str = "robust"

    def __post_init__(self) -> None:
        if self.mode not in ("robust", "seed"):
            raise InputError(f"mode: expected 'robust' or 'seed', got {self.mode!r}")

    @classmethod
    def from_calibration(cls, calibration: dict) -> InputProcessing:
        """The processing a calibration JSON (docs/formats.md) implies."""
        try:
            params = HoloParams(*(float(calibration["params"][key]) for key in ("N_R", "N_sigma", "gamma")))
        except (KeyError, TypeError, ValueError) as error:
            raise InputError(f"calibration: expected params N_R, N_sigma and gamma, missing or invalid {error}") from None
        mode = (calibration.get("settings") or {}).get("mode", "robust")
        return cls(params=params, invert_experiment=True, mode=mode)

    def to_dict(self) -> dict:
        return {"params": self.params.as_dict(), "invert_experiment": self.invert_experiment, "mode": self.mode}

    @classmethod
    def from_dict(cls, payload: dict) -> InputProcessing:
        return cls(params=HoloParams(**payload["params"]), invert_experiment=bool(payload["invert_experiment"]), mode=payload["mode"])


@dataclass(frozen=True)
class DatasetLayout:
    """Which planes a data set stores and where its particles sit.

    Attributes
    ----------
    kind : {"stack", "layers"}
        See the module docstring.
    context_planes : int
        ``stack``: planes stored beyond each end of the reconstruction grid, so the planes around
        the first and last depths exist too (a model's context reach must not exceed it).
    depths : {"uniform", "layers"}
        ``stack``: particle depths uniform over ``z_min_um`` … ``z_max_um`` or on the seed's
        layers (every ``layer_step_um``).
    """

    kind: str = "stack"
    context_planes: int = 8
    depths: str = "uniform"

    def __post_init__(self) -> None:
        if self.kind not in ("stack", "layers"):
            raise InputError(f"layout: expected 'stack' or 'layers', got {self.kind!r}")
        if self.depths not in ("uniform", "layers"):
            raise InputError(f"depths: expected 'uniform' or 'layers', got {self.depths!r}")
        if not 0 <= int(self.context_planes) <= 64:
            raise InputError(f"context_planes: expected 0..64 planes, got {self.context_planes!r}")

    def planes_um(self, config: ExperimentConfig) -> tuple[float, ...]:
        """The depths (µm) whose input planes a group stores."""
        if self.kind == "layers":
            return config.layer_depths_um()
        grid = config.volume.planes_um()
        step = config.volume.z_step_um
        margin = int(self.context_planes)
        return tuple(grid[0] + i * step for i in range(-margin, 0)) + grid + tuple(grid[-1] + i * step for i in range(1, margin + 1))

    def to_dict(self) -> dict:
        return {"kind": self.kind} if self.kind == "layers" else {"kind": self.kind, "context_planes": int(self.context_planes), "depths": self.depths}

    @classmethod
    def from_dict(cls, payload: dict | None) -> DatasetLayout:
        return cls(kind="layers") if not payload or payload.get("kind") == "layers" else cls(**payload)


def synthetic_group(
    config: ExperimentConfig,
    processing: InputProcessing,
    *,
    seed: int | list[int],
    shape: tuple[int, int] | None = None,
    count: int | None = None,
    layout: DatasetLayout = DatasetLayout(kind="layers"),
    effects: dict | None = None,
    distractors: Distractors = Distractors(),
    sizes: SizeDistribution | None = None,
) -> tuple[np.ndarray, np.ndarray, ParticleField]:
    """One training group: ``(inputs, labels, field)``.

    Parameters
    ----------
    config : ExperimentConfig
        Optics, particle sizes, layers (``z_min_um`` … ``z_max_um`` every ``layer_step_um``).
    processing : InputProcessing
        Holo-processing applied to the simulated hologram.
    seed : int or list of int
        Seeds the particle field and the noise.
    shape, count : optional
        Window (default ``tile.size`` square) and particle count (default ``per_tile``).
    layout : DatasetLayout
        Which planes to make and where particles sit (default: the seed's layers).
    effects : dict, optional
        Effects of the catalog added to the simulated hologram (`effect_hologram`); none: the
        seed's opaque discs.
    distractors : Distractors
        Unlabelled impurities and neighbours outside the window, simulated with the particles
        (`distractor_scene`); default none, the seed's scene.
    sizes : SizeDistribution, optional
        The particles' (and neighbours') diameters, drawn within the config's range (from a
        diagnosis: `sizes_from_report`); default uniform over it, the seed's.

    Returns
    -------
    inputs, labels : (len(layout.planes_um(config)), rows, cols) float32
    field : ParticleField
    """
    rng = np.random.default_rng(seed)
    planes_um = layout.planes_um(config)
    size = config.tile.size
    on_layers = layout.kind == "layers" or layout.depths == "layers"
    diameter_range_um = (config.particles.diameter_min_um, config.particles.diameter_max_um)
    particles = random_particle_field(
        shape or (size, size),
        count=config.particles.per_tile if count is None else count,
        diameter_min_um=diameter_range_um[0],
        diameter_max_um=diameter_range_um[1],
        layers_um=config.layer_depths_um() if on_layers else (config.volume.z_min_um, config.volume.z_max_um),
        continuous=not on_layers,
        pixel_um=config.optics.pixel_um,
        seed=rng,
        sizes=sizes,
    )
    # the optics sees the particles and the distractors; the labels only the particles
    scene = distractor_scene(particles, distractors, tile_px=size, depth_range_um=(config.volume.z_min_um, config.volume.z_max_um), diameter_range_um=diameter_range_um,
                             layers_um=config.layer_depths_um() if on_layers else None, sizes=sizes, rng=rng)
    margin = distractors.neighbours_margin_px
    optics = {"wavelength_um": config.optics.wavelength_um, "medium_index": config.optics.medium_index}
    if effects:
        hologram = effect_hologram(scene, effects, crop_px=margin, rng=rng, **optics)
    else:
        hologram = simulate_hologram(scene, **optics)
        hologram = np.ascontiguousarray(hologram[margin:-margin, margin:-margin]) if margin else hologram
    inputs = holo_processing(hologram, processing.params, planes_um=planes_um, pixel_um=config.optics.pixel_um, seed=rng, mode=processing.mode, average=False, **optics)
    return inputs, label_planes(particles, planes_um), particles


@dataclass(frozen=True)
class SyntheticDataset:
    """A data set folder: its description and the groups present on disk."""

    path: Path
    spec: dict
    groups: list[int]
    complete: bool
    stopped: bool = False

    @property
    def config(self) -> ExperimentConfig:
        return ExperimentConfig.from_dict(self.spec["config"])

    @property
    def processing(self) -> InputProcessing:
        return InputProcessing.from_dict(self.spec["processing"])

    @property
    def planes_um(self) -> list[float]:
        return list(self.spec["planes_um"])

    @property
    def layout(self) -> DatasetLayout:
        return DatasetLayout.from_dict(self.spec.get("layout"))

    def group_path(self, group: int) -> Path:
        return self.path / "groups" / f"group_{group:05d}.tif"

    def read_group(self, group: int) -> tuple[np.ndarray, np.ndarray, dict]:
        """``(inputs, labels, description)`` of one group."""
        import tifffile

        path = self.group_path(group)
        if not path.is_file():
            raise InputError(f"{path}: group file not found")
        try:
            with tifffile.TiffFile(path) as handle:
                inputs = handle.series[0].asarray()
                labels = handle.series[1].asarray()
                description = json.loads(handle.pages[0].description)
        except Exception as error:  # truncated, overwritten, not a TIFF: the file is the culprit
            raise InputError(f"{path}: corrupt group file ({type(error).__name__}); delete it and run generate again to rebuild it") from None
        return inputs, labels, description

    def arrays(self, groups: list[int], *, dtype=np.float32) -> tuple[np.ndarray, np.ndarray, list[dict]]:
        """Input and label planes of ``groups``, two ``(len(groups), n_planes, rows, cols)`` arrays, and their particle tables."""
        size, planes = self.spec["tile_size"], len(self.spec["planes_um"])
        inputs = np.empty((len(groups), planes, size, size), dtype)
        labels = np.empty((len(groups), planes, size, size), np.float32)
        tables = []
        for index, group in enumerate(groups):
            inputs[index], labels[index], description = self.read_group(group)
            tables.append({key: np.asarray(values, np.float64) for key, values in description["particles"].items()})
        return inputs, labels, tables


def _spec(config: ExperimentConfig, processing: InputProcessing, layout: DatasetLayout, seed: int, effects: dict, distractors: Distractors,
          sizes: SizeDistribution | None) -> dict:
    spec = {
        "format": DATASET_FORMAT,
        "version": _FORMAT_VERSION,
        "config": config.to_dict(),
        "processing": processing.to_dict(),
        "layout": layout.to_dict(),
        "seed": int(seed),
        "planes_um": [float(z) for z in layout.planes_um(config)],
        "tile_size": int(config.tile.size),
        "particles_per_group": int(config.particles.per_tile),
    }
    if effects:  # absent when none, so sets made before effects existed still extend
        spec["effects"] = effects
    if distractors.active:  # likewise
        spec["distractors"] = distractors.to_dict()
    if sizes is not None:  # likewise
        spec["sizes"] = sizes.to_dict()
    return spec


_IDENTITY_KEYS = ("format", "version", "config", "processing", "layout", "effects", "distractors", "sizes", "seed", "planes_um", "tile_size", "particles_per_group")


def _group_is_valid(path: Path, planes: int, size: int) -> bool:
    import tifffile

    try:
        with tifffile.TiffFile(path) as handle:
            return len(handle.series) == 2 and all(s.shape == (planes, size, size) for s in handle.series)
    except Exception:  # an unreadable file is simply regenerated
        return False


def generate_dataset(
    out_dir: str | Path,
    config: ExperimentConfig,
    *,
    groups: int,
    processing: InputProcessing = InputProcessing(),
    layout: DatasetLayout = DatasetLayout(),
    calibration: dict | None = None,
    effects: dict | None = None,
    effects_source: dict | None = None,
    distractors: Distractors = Distractors(),
    sizes: SizeDistribution | None = None,
    seed: int = 0,
    workers: int = 1,
    progress: ProgressCallback | None = None,
    should_stop: StopCallback | None = None,
) -> SyntheticDataset:
    """Write ``groups`` synthetic groups into ``out_dir`` (the `napari-lbs generate` step).

    Resumable: groups already in ``out_dir`` from the same settings are kept, so a stopped
    or interrupted run continues where it ended, and asking for more groups extends a set. A
    folder holding a set made with other settings is refused rather than mixed.

    Parameters
    ----------
    out_dir : path
        The data set folder (created if needed).
    config : ExperimentConfig
    groups : int
        Number of groups (the seed: 256).
    processing : InputProcessing
        How synthetic planes are processed (`InputProcessing.from_calibration`).
    layout : DatasetLayout
        Which planes each group stores (default: the reconstruction stack with context).
    calibration : dict, optional
        The calibration JSON, recorded as provenance.
    effects : dict, optional
        ``{effect_id: {param: value}}`` added to every simulated hologram (`effect_hologram`;
        from a diagnosis: `effects_from_report`). Recorded in ``dataset.json`` and part of the
        set's identity.
    effects_source : dict, optional
        Where the effects came from (e.g. the report's path and verdict), recorded as provenance.
    distractors : Distractors
        Unlabelled impurities and out-of-window neighbours in every group (`distractor_scene`).
        Recorded in ``dataset.json`` and part of the set's identity. The impurities must be
        smaller than the particles (``impurity_diameter_max_um`` < ``diameter_min_um``), or
        the labels would contradict each other.
    sizes : SizeDistribution, optional
        The particles' diameter distribution within the config's range (`synthetic_group`).
        Recorded in ``dataset.json`` and part of the set's identity.
    seed : int
    workers : int
        Processes simulating groups at once (1: in this process; at most `available_threads`;
        `run_in_workers`). The set does not depend on it.
    progress, should_stop
        One step per group. A stop ends after the current group in this process, at once in
        workers (a group they were writing is left out); the set is then marked incomplete and
        a rerun finishes it.
    """
    if int(groups) < 1:
        raise InputError(f"groups: expected a positive number of groups, got {groups}")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: expected a folder for the data set, got a file")
    effects = check_effects(effects or {})
    if distractors.impurities_per_tile and distractors.impurity_diameter_max_um >= config.particles.diameter_min_um:
        raise InputError(f"impurity_diameter_max_um: expected a diameter below the particles' diameter_min_um={config.particles.diameter_min_um:g} µm, got {distractors.impurity_diameter_max_um:g} µm")
    spec = _spec(config, processing, layout, seed, effects, distractors, sizes)
    manifest = out / "dataset.json"
    if manifest.is_file():
        existing = read_json_object(manifest, what="data set manifest")
        # a set stated before an effect gained optional parameters holds them switched off: the same images
        if existing.get("effects"):
            existing["effects"] = check_effects(existing["effects"])
        differing = [key for key in _IDENTITY_KEYS if existing.get(key) != spec.get(key)]
        if differing:
            raise InputError(f"{out}: holds a data set made with other settings (differs in {', '.join(differing)}); choose another folder")
    spec.update(groups=int(groups), calibration=calibration, napari_lbs=__version__)
    if effects:
        spec["effects_source"] = effects_source
    (out / "groups").mkdir(parents=True, exist_ok=True)
    write_json(manifest, {**spec, "complete": False})
    dataset = SyntheticDataset(out, spec, [], complete=False)  # its group paths
    planes_um = spec["planes_um"]
    steps = Steps(int(groups), progress=progress, should_stop=should_stop)
    valid = {g: _group_is_valid(dataset.group_path(g), len(planes_um), config.tile.size) for g in range(int(groups))}
    present, missing = [g for g, ok in valid.items() if ok], [g for g, ok in valid.items() if not ok]
    written, stopped = list(present), False
    if present:
        steps.advance(len(present))
    jobs = [(dataset.group_path(g), config, processing, layout, effects, distractors, sizes, int(seed), g) for g in missing]
    try:
        written.extend(run_in_workers(_write_job, jobs, workers=workers, steps=steps))
    except Stopped:
        # each group is written atomically: the ones on disk are whole, whichever worker wrote them
        stopped = True
        written.extend(g for g in missing if _group_is_valid(dataset.group_path(g), len(planes_um), config.tile.size))
    dataset = replace(dataset, groups=sorted(written), complete=len(written) == int(groups), stopped=stopped)
    write_json(manifest, {**spec, "complete": dataset.complete})
    return dataset


def _write_job(job: tuple) -> int:
    """`_write_group` of one job's arguments (a worker's task)."""
    return _write_group(*job)


def _write_group(path: Path, config: ExperimentConfig, processing: InputProcessing, layout: DatasetLayout, effects: dict, distractors: Distractors,
                 sizes: SizeDistribution | None, seed: int, group: int) -> int:
    """Simulate group ``group`` and write its file atomically (runs in a worker process too)."""
    import tifffile

    inputs, labels, particles = synthetic_group(config, processing, seed=[seed, group], layout=layout, effects=effects, distractors=distractors, sizes=sizes)
    if layout.kind == "stack":  # values in [0, 1]: float16 keeps 11 bits and halves the cache
        inputs = inputs.astype(np.float16)
    _check_group(path, inputs, labels, effects)
    description = json.dumps({
        "group": group,
        "seed": [seed, group],
        "z_um": [float(z) for z in layout.planes_um(config)],
        "particles": {key: [float(v) for v in values] for key, values in particles.table().items()},
    })
    with atomic_path(path) as temporary, tifffile.TiffWriter(temporary) as writer:
        writer.write(inputs, description=description, metadata=None, photometric="minisblack")
        writer.write(labels, compression="zlib", metadata=None, photometric="minisblack")
    return group


def _check_group(path: Path, inputs: np.ndarray, labels: np.ndarray, effects: dict) -> None:
    """Refuse a group that holds no usable hologram, before its file is put in place (a set with such a group would train on garbage)."""
    for what, values in (("inputs", inputs), ("labels", labels)):
        bad = int(np.size(values) - np.count_nonzero(np.isfinite(values)))
        if bad:
            raise InputError(f"{path.name}: the {what} hold {bad} NaN or infinite values; the settings (effects {effects or 'none'}) make no valid hologram")
    if not np.any(inputs):
        raise InputError(f"{path.name}: the inputs are all zero; the settings (effects {effects or 'none'}) make no valid hologram")


def open_dataset(path: str | Path) -> SyntheticDataset:
    """Open a data set folder written by `generate_dataset`."""
    path = Path(path)
    manifest = path / "dataset.json"
    if not manifest.is_file():
        raise InputError(f"{path}: not a napari-lbs data set (no dataset.json)")
    spec = check_dataset_manifest(read_json_object(manifest, what="data set manifest"), name=str(manifest), formats={DATASET_FORMAT: (1, _FORMAT_VERSION)})
    dataset = SyntheticDataset(path, spec, [], complete=bool(spec.get("complete")))  # its group paths
    return replace(dataset, groups=[g for g in range(int(spec["groups"])) if dataset.group_path(g).is_file()])


def dataset_summary(dataset: SyntheticDataset) -> dict:
    """What a training log records about its data."""
    summary = {
        "path": str(dataset.path),
        "groups": len(dataset.groups),
        "complete": dataset.complete,
        "layout": dataset.layout.to_dict(),
        **{k: dataset.spec[k] for k in ("seed", "planes_um", "tile_size", "processing")},
    }
    if dataset.spec.get("effects"):  # absent when none, so training states saved before effects existed still resume
        summary["effects"] = dataset.spec["effects"]
    if dataset.spec.get("distractors"):  # likewise
        summary["distractors"] = dataset.spec["distractors"]
    if dataset.spec.get("sizes"):  # likewise
        summary["sizes"] = dataset.spec["sizes"]
    return summary

