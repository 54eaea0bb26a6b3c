"""The steps that find particles: predict (a hologram or a recording, refined by a fit on request) and track."""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Sequence
from dataclasses import KW_ONLY, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

from napari_lbs._core.foundation import ExperimentConfig
from napari_lbs._core.foundation import InputError
from napari_lbs._core.foundation import ProgressCallback, StopCallback, WorkerPool, begin_phase
from napari_lbs._core.foundation import check_output_path, check_target, write_json
from napari_lbs._core.pipeline._common import Log, StepResult, _background, _quiet, _source

if TYPE_CHECKING:  # for the annotations only: the steps import these modules when they run
    import numpy as np

    from napari_lbs._core.learning import LoadedModel, PredictionResult, PredictionSettings
    from napari_lbs._core.refine import RefineSettings

__all__ = ["PredictRequest", "REFINE_PROPOSAL_FRACTION", "refined_prediction", "prediction_outputs", "predict", "TrackRequest", "track"]


# --- predict -------------------------------------------------------------------------------


@dataclass(frozen=True)
class PredictRequest:
    """The particles of a hologram or a recording, found by a trained model.

    Attributes
    ----------
    inputs : sequence of paths, or a 2-D array
        Image files, folders, glob patterns, multi-page TIFFs or videos (`open_frames`); frames
        numbered in this order. An array is one hologram already read.
    model : path or LoadedModel
    out_path : Path
        The particle table (CSV, or Parquet for ``.parquet``); provenance beside it as ``.json``.
    config : ExperimentConfig, optional
        Optics and depths (default: the model's).
    background_path : path, optional
        A hologram taken without particles, divided out of every frame.
    device : str
    precision : str
        The network's arithmetic: ``auto``, ``float32`` or ``bfloat16`` (`resolve_precision`).
    force : bool
        Run a model made for other optics or depths than the config's.
    sequence_background : str
        Recordings without a background file: ``auto``, ``global``, ``running``, ``flat`` or ``none`` (`predict_sequence`).
    background_window : int
        Frames of a running background.
    workers : int, optional
        Recordings: a local dask cluster of this many workers.
    scheduler : str, optional
        Recordings: an existing dask.distributed scheduler's address.
    source : str, optional
        The hologram's name in the provenance when ``inputs`` is an array.
    refine : bool
        Refine every detection by a Lorenz–Mie fit (`refine_particles`); the table gains its columns.
    threshold : float, optional
        The smallest score a detection keeps (`predict_particles`); default the model's, and
        with ``refine`` `REFINE_PROPOSAL_FRACTION` of it.
    material_index_contrast : float, optional
        The sample's ``n_p - n_m`` (implies ``refine``); particles of another material
        (`same_material`) are listed in the provenance instead of the table.
    replace : bool
        Replace existing outputs (the user's ``--force``, or a save dialog that asked); links, devices and FIFOs are refused regardless.
    """

    inputs: Sequence[str | Path] | np.ndarray
    model: str | Path | LoadedModel
    out_path: Path
    config: ExperimentConfig | None = None
    _: KW_ONLY  # the data above, the options below
    background_path: str | Path | None = None
    device: str = "auto"
    precision: str = "auto"
    force: bool = False
    sequence_background: str = "auto"
    background_window: int = 21
    workers: int | None = None
    scheduler: str | None = None
    source: str | None = None
    refine: bool = False
    threshold: float | None = None
    material_index_contrast: float | None = None
    replace: bool = False

    def outputs(self) -> tuple[Path, Path]:
        """The files the step writes: the table and its provenance beside it (checked by `prediction_outputs`)."""
        return Path(self.out_path), Path(self.out_path).with_suffix(".json")

    def settings(self) -> PredictionSettings:
        """The network's options (`PredictionSettings`): ``threshold``, ``device``, ``precision`` and ``force``."""
        from napari_lbs._core.learning import PredictionSettings

        return PredictionSettings(threshold=self.threshold, device=self.device, precision=self.precision, force=self.force)


# With a fit to check them, detections are proposed at this fraction of the model's score
# threshold: on the development holograms of docs/refinement.md the fit turned the extra
# proposals into the spheres the network had scored just below its threshold (sizes beyond
# its training range, overlapping holograms), and kept few false ones, down to 0.8 of it.
REFINE_PROPOSAL_FRACTION = 0.8


def _proposal_threshold(meta: dict, threshold: float | None) -> float:
    """The score down to which a refined prediction proposes: ``threshold``, else `REFINE_PROPOSAL_FRACTION` of the model's."""
    return float(threshold) if threshold is not None else REFINE_PROPOSAL_FRACTION * float(meta["threshold"])


def _acceptance_threshold(meta: dict, threshold: float | None) -> float:
    """The score a detection the fit could not refine needs to stay: ``threshold``, else the model's own."""
    return float(threshold) if threshold is not None else float(meta["threshold"])


def _network_proposals(model, config: ExperimentConfig | None, settings: PredictionSettings, *, progress, should_stop):
    """``propose(image)``: the network's proposals with ``settings`` (`PredictionSettings`, its threshold the proposals') in an image as the fit sees it (divided by the background, else by its mean), for `residual_particles`."""
    from napari_lbs._core.learning import predict_particles

    return lambda image: predict_particles(image, model, config, settings=settings, progress=progress, should_stop=should_stop).particles


def _network_depth_error_um(meta: dict) -> float:
    """The model's validated median depth error ``|Δz|`` (µm, the config's convention), 0 where its file records none."""
    value = (meta.get("validation") or {}).get("median_abs_dz_um")
    return float(value) if isinstance(value, int | float) and math.isfinite(value) and value > 0 else 0.0


def _fit_settings(settings: RefineSettings | None, config: ExperimentConfig, *, device: str, material: float | None, depth_prior_um: float = 0.0) -> RefineSettings:
    """The `RefineSettings` of a refined prediction: ``settings``, else the prediction's device with one fitting process per available core, the ``refine`` command's depth window for ``config`` (`default_depth_window_um`) and the network's validated depth error as the fits' depth prior (``depth_prior_um``); a declared ``material`` is where every fit starts."""
    from napari_lbs._core.foundation import available_threads
    from napari_lbs._core.pipeline._binning import default_depth_window_um
    from napari_lbs._core.refine import RefineSettings

    start = {} if material is None else {"index_contrast": float(material)}
    if settings is None:  # the prediction's device (CUDA where it ran there); on the CPU one fitting process per core
        return RefineSettings(device=device, workers=available_threads(), depth_window_um=default_depth_window_um(config), depth_prior_um=depth_prior_um, **start)
    return replace(settings, **start)


def refined_prediction(hologram: np.ndarray, model, config: ExperimentConfig | None = None, *, background: np.ndarray | None = None, device: str = "auto",
                       precision: str = "auto", force: bool = False, threshold: float | None = None, material_index_contrast: float | None = None,
                       settings: PredictionSettings | None = None, refine_settings: RefineSettings | None = None,
                       progress: ProgressCallback | None = None, should_stop: StopCallback | None = None) -> PredictionResult:
    """The particles of one hologram as ``napari-lbs predict --refine`` finds them: the network, a fit of every detection, a second look in the residual.

    `predict_particles` proposes down to `REFINE_PROPOSAL_FRACTION` of the model's threshold
    (or the given threshold), then `refine_particles` fits every proposal on the hologram
    divided by ``background``, else by its mean. The network then looks again in what the
    refined table leaves unexplained (`residual_particles`: spheres hidden in their
    neighbours' fringes, sizes it scored low), the sample's particles the fit measures
    there join the table, and every particle is refitted with them in its model.

    Parameters
    ----------
    hologram : (rows, cols) array
        Intensity hologram.
    model : LoadedModel or path
        A model file from `train_model`.
    config : ExperimentConfig, optional
        Optics and depths; default the model's own.
    background : (rows, cols) array, optional
        Hologram without particles.
    device, precision, force, threshold
        The network's options (`predict_particles`); ``threshold`` is the proposals'.
    material_index_contrast : float, optional
        The sample's ``n_p - n_m``: the fits start there, and the particles of another
        material (`same_material`) leave the table for the provenance's
        ``refine.material.other_particles``.
    settings : PredictionSettings, optional
        The network's options in one object instead of the keywords (a call gives one or the
        other).
    refine_settings : RefineSettings, optional
        How the fits run; default ``RefineSettings(device=device, workers=<available cores>)``
        (more than 1 worker spawns processes: a script's ``if __name__ == "__main__":`` guard).
    progress, should_stop
        ``progress`` counts the prediction's planes, then the fit's batches, then the same for
        the second look, each phase named as it begins (`begin_phase`: "network",
        "fit N particles", "second look"); a stop raises `Stopped`.

    Returns
    -------
    PredictionResult
        Particles: the refined table (`refine_particles`' columns after the first four).
        Provenance: the network's, plus ``refine`` (settings, counts, seconds; ``residual``:
        the second look's proposals, finds and seconds; ``material`` with
        ``material_index_contrast``).
    """
    import numpy as np

    from napari_lbs._core.learning import LoadedModel, load_model
    from napari_lbs._core.learning import PredictionResult, predict_particles, prediction_settings
    from napari_lbs._core.refine import unsaturated_pixels

    started = time.perf_counter()
    settings = prediction_settings(settings, device=device, precision=precision, force=force, threshold=threshold)
    model = model if isinstance(model, LoadedModel) else load_model(model, device=settings.device)
    accept = _acceptance_threshold(model.meta, settings.threshold)
    settings = replace(settings, threshold=_proposal_threshold(model.meta, settings.threshold))
    begin_phase(progress, "network")
    result = predict_particles(hologram, model, config, background=background, settings=settings, progress=progress, should_stop=should_stop)
    normalised = np.asarray(hologram, dtype=np.float64) / (background if background is not None else float(np.mean(hologram)))
    propose = _network_proposals(model, config, settings, progress=progress, should_stop=should_stop)
    fit = _fit_settings(refine_settings, config or model.config, device=settings.device, material=material_index_contrast,
                        depth_prior_um=_network_depth_error_um(model.meta))
    with WorkerPool(fit.workers) as pool:  # the frame's fits' processes, started once
        particles, record = _refined(normalised, result.particles, config or model.config, fit, material=material_index_contrast, propose=propose,
                                     valid=unsaturated_pixels(hologram), progress=progress, should_stop=should_stop, accept_score=accept, pool=pool)
    return PredictionResult(particles, {**result.provenance, "refine": record}, time.perf_counter() - started)


def prediction_outputs(out_path, *, replace: bool = False, marker: str = "model_sha256") -> tuple[Path, Path]:
    """The particle table and its provenance JSON beside it, refused where they exist (unless ``replace``) or would overwrite something else.

    Even with ``replace`` an existing ``.json`` is replaced only when it is this table's
    provenance from an earlier run of the same step (it names the table and holds
    ``marker``: a prediction's ``model_sha256``, a refinement's ``find``), never a model's
    training log or another file.
    """
    from napari_lbs._core.foundation import check_table_name

    out = Path(out_path)
    if out.suffix.lower() == ".json":
        raise InputError(f"--out {out}: expected a particle table (.csv, or .parquet); its provenance is written beside it as .json")
    check_table_name(out)  # a Parquet table without pyarrow is refused now, not after the work
    record = out.with_suffix(".json")
    check_target(out, force=replace, flag="--out")
    if check_target(record, force=replace, flag="--out").is_file():
        try:
            previous = json.loads(record.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError):
            previous = None
        # only a previous run's provenance of this same table may be replaced (never a model's training log)
        if not (isinstance(previous, dict) and previous.get("particles") == str(out) and marker in previous):
            raise InputError(f"--out {out}: {record} exists and is not this table's provenance; choose another name")
    return out, record


def _write_table(out: Path, record_path: Path, particles: dict, record: dict) -> None:
    """The particle table (CSV, or Parquet with ``record`` in its key-value metadata too) and its provenance JSON beside it."""
    from napari_lbs._core.foundation import write_particles

    write_particles(out, particles, metadata=record, force=True)  # prediction_outputs checked it with the user's --force
    write_json(record_path, record)


def predict(request: PredictRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None, log: Log = _quiet) -> StepResult:
    """Predict the particles of one hologram, or of every frame of a recording (one table with a ``frame`` column)."""
    from napari_lbs._core.learning import load_model
    from napari_lbs._core.learning import predict_particles
    from napari_lbs._core.recordings import open_frames

    out, record_path = prediction_outputs(request.out_path, replace=request.replace)
    if isinstance(request.inputs, (str, Path, list, tuple)):
        inputs = [request.inputs] if isinstance(request.inputs, (str, Path)) else list(request.inputs)
        with open_frames(inputs) as frames:
            if len(frames) > 1:
                return _predict_recording(request, frames, out, record_path, progress=progress, should_stop=should_stop, log=log)
            # one frame (an image, a one-page TIFF, a one-frame video): the single-hologram path
            source, hologram = frames.name(0), frames.read(0, log=log)
    else:
        source, hologram = _source("array", request.source), request.inputs
    background = _background(request.background_path, hologram.shape, log=log)
    model = request.model if not isinstance(request.model, (str, Path)) else load_model(request.model, device=request.device)
    options = {"background": background, "settings": request.settings(), "progress": progress, "should_stop": should_stop}
    refine = request.refine or request.material_index_contrast is not None  # the fit measures the material
    if refine:
        options["material_index_contrast"] = request.material_index_contrast
    result = (refined_prediction if refine else predict_particles)(hologram, model, request.config, **options)
    particles, provenance = result.particles, result.provenance
    refined = _refine_summary(provenance["refine"]) if refine else ""
    _write_table(out, record_path, particles, {**provenance, "source": str(source), "background_file": request.background_path, "particles": str(out)})
    count = provenance["refine"]["detections"] if refine else len(particles["x_um"])
    return StepResult(f"found {count} particles in {source} in {result.seconds:.1f} s{refined} -> {out} (provenance: {record_path})", result, (out, record_path))


def _refine_summary(record: dict) -> str:
    """What the fit did, for a prediction's one-line summary."""
    line = f", {record['kept']} kept by the fit in {record['seconds']:.1f} s, {record['residual']['found']} more found in its residual"
    if record.get("unconfirmed"):
        line += f", {record['unconfirmed']} proposals below the model's threshold that the fit could not refine left out"
    if "material" in record:
        line += f", {record['material']['other_material']} of another material than {record['material']['index_contrast']:g} left out"
    return line


def _refined_frames(frames, particles: dict, config: ExperimentConfig, settings: RefineSettings, *, background, material: float | None, propose, log: Log, progress,
                    should_stop, accept_score: float | None = None) -> tuple[dict, dict]:
    """Each frame's rows of a recording's table refined with ``settings`` on that frame (divided by the background file, else by its mean); ``accept_score`` as `_refined`'s."""
    import numpy as np

    from napari_lbs._core.refine import unsaturated_pixels

    frame_of = np.asarray(particles["frame"]).astype(np.int64)
    parts, records = [], []
    with WorkerPool(settings.workers) as pool:  # the fitting processes start once for the recording
        for index in np.unique(frame_of):
            rows = frame_of == index
            hologram = np.asarray(frames.read(int(index), log=log), dtype=np.float64)
            divisor = background if isinstance(background, np.ndarray) else float(hologram.mean())
            table, record = _refined(hologram / divisor, {name: np.asarray(values)[rows] for name, values in particles.items()}, config, settings, material=material,
                                     propose=propose, valid=unsaturated_pixels(hologram), progress=progress, should_stop=should_stop, accept_score=accept_score,
                                     pool=pool)
            if len(table["x_um"]) and "frame" in table:
                table["frame"] = np.full(len(table["x_um"]), index, dtype=np.asarray(particles["frame"]).dtype)
            parts.append(table)
            records.append(record)
    merged = {name: np.concatenate([part[name] for part in parts]) for name in parts[0]} if parts else particles
    summary = {"settings": records[0]["settings"] if records else None, "detections": sum(r["detections"] for r in records),
               "kept": sum(r["kept"] for r in records), "seconds": sum(r["seconds"] for r in records), "pixels_left_out": sum(r["pixels_left_out"] for r in records),
               "refit": {key: sum(r.get("refit", {}).get(key, 0) for r in records) for key in ("particles", "kept")},
               "residual": {key: sum(r["residual"][key] for r in records) for key in ("proposals", "found", "seconds")}}
    if accept_score is not None:
        summary["unconfirmed"] = sum(r.get("unconfirmed", 0) for r in records)
    if material is not None:
        from napari_lbs._core.refine import MATERIAL_SIGMAS, MATERIAL_TOLERANCE

        others = [r["material"]["other_particles"] for r in records]
        summary["material"] = {"index_contrast": float(material), "tolerance": MATERIAL_TOLERANCE, "sigmas": MATERIAL_SIGMAS,
                               "other_material": sum(r["material"]["other_material"] for r in records),
                               "other_particles": {name: [value for table in others for value in table[name]] for name in (others[0] if others else particles)}}
    return merged, summary


def _refined(hologram: np.ndarray, particles: dict, config: ExperimentConfig, settings: RefineSettings, *, material: float | None, propose,
             valid: np.ndarray | None, progress, should_stop, pool: WorkerPool, accept_score: float | None = None) -> tuple[dict, dict]:
    """The particle table refined by `refine_particles` with ``settings``, with the finds in its residual (`residual_particles`, ``propose``), of the ``material`` where given (as a dict of arrays), and its provenance.

    As the ``refine`` command does, a pitch finer than half the medium wavelength is binned
    for the fit (`binned_hologram`: 2 × 2 at a microscope's 0.1 µm in water), so its patches
    reach twice as far and see the fringes of a sphere 50 µm from focus at angles that tell
    its depth; the network's second look sees the binned residual at its trained pitch,
    each binned pixel's value over its block. Positions are reported in the hologram's own
    coordinates. Where the second look finds particles, every refined particle is fitted
    again with them in its neighbours' model (two rounds, each started at its fit and at the
    settings' index contrast), as `refine`'s looks do (the provenance's ``refit``), and a row
    the first fit could not refine leaves the table once a refined particle lies on it.
    ``valid``: the pixels the fits compare (`unsaturated_pixels` of the raw frame: a
    saturated camera's clipped pixels left out), the provenance's ``pixels_left_out``.
    ``accept_score``: the network's own threshold. A proposal scored below it was made for
    the fit to judge; one the fit could not refine leaves the table (the provenance's
    ``unconfirmed``), where one at or above it stays at the network's guess. ``pool``: the
    processes the three fits run in (a `WorkerPool` of ``settings.workers``, kept by the caller).
    """
    from dataclasses import asdict

    import numpy as np
    import pandas as pd

    from napari_lbs._core.pipeline._binning import binned_hologram, binned_valid
    from napari_lbs._core.pipeline._common import explained_by_fits
    from napari_lbs._core.refine import MATERIAL_SIGMAS, MATERIAL_TOLERANCE, same_material
    from napari_lbs._core.refine import refine_particles
    from napari_lbs._core.refine import residual_particles

    started = time.perf_counter()
    image, fit_config, shift_um = binned_hologram(hologram, config, medium_index=settings.medium_index)
    fit_valid = binned_valid(valid, config, medium_index=settings.medium_index)
    factor = int(round(fit_config.optics.pixel_um / config.optics.pixel_um))
    guesses = pd.DataFrame(particles)
    guesses[["x_um", "y_um"]] = guesses[["x_um", "y_um"]].astype(np.float64) - shift_um
    begin_phase(progress, f"fit {len(particles['x_um'])} particles")
    table = refine_particles(image, guesses, fit_config, settings=settings, valid=fit_valid, progress=progress, should_stop=should_stop, pool=pool)
    record = {"settings": asdict(settings), "binning": factor, "detections": len(particles["x_um"]), "kept": len(table), "seconds": time.perf_counter() - started,
              "pixels_left_out": 0 if valid is None else int(np.count_nonzero(~valid))}
    started = time.perf_counter()
    proposals = []

    def counted(binned):
        # the network's proposals at its own pitch, in the binned frame's coordinates
        found = dict(propose(np.repeat(np.repeat(binned, factor, axis=0), factor, axis=1)))
        proposals.append(found)
        return {**found, "x_um": np.asarray(found["x_um"]) - shift_um, "y_um": np.asarray(found["y_um"]) - shift_um}

    found = ()
    if len(table) and table["refined"].any():  # with nothing refined, the residual is the hologram the network has seen
        begin_phase(progress, "second look")
        found = residual_particles(image, table, fit_config, propose=counted, settings=settings, background=np.ones(image.shape), valid=fit_valid, progress=progress,
                                   should_stop=should_stop, pool=pool)
    record["residual"] = {"proposals": len(pd.DataFrame(dict(proposals[0]))) if proposals else 0, "found": len(found)}
    if len(found):
        # every particle refitted with the finds in its neighbours' model, as `refine`'s looks do:
        # a sphere's fringes reach tens of micrometres, and a miss's pulled its neighbours' fits
        refined = table["refined"].astype(bool).to_numpy()
        restart = pd.concat([table[refined], found], ignore_index=True)
        restart["index_contrast"] = settings.index_contrast  # the start's valley, not one a missed neighbour pulled a fit into
        begin_phase(progress, f"refit {len(restart)} particles")
        refit = refine_particles(image, restart, fit_config, settings=replace(settings, rounds=max(settings.rounds, 2)), valid=fit_valid, progress=progress,
                                 should_stop=should_stop, pool=pool)
        pending = table[~refined]
        table = pd.concat([refit, pending[~explained_by_fits(pending, refit)]], ignore_index=True)
        record["refit"] = {"particles": len(restart), "kept": len(refit)}
    record["residual"]["seconds"] = time.perf_counter() - started  # the second look and the refit it asks for
    table[["x_um", "y_um"]] += shift_um
    if accept_score is not None and "score" in table:
        unconfirmed = ~table["refined"].astype(bool).to_numpy() & (table["score"].to_numpy() < accept_score)
        record["unconfirmed"] = int(unconfirmed.sum())
        table = table[~unconfirmed]
    if material is not None:
        member = same_material(table, index_contrast=material, tolerance=MATERIAL_TOLERANCE, sigmas=MATERIAL_SIGMAS)
        record["material"] = {"index_contrast": float(material), "tolerance": MATERIAL_TOLERANCE, "sigmas": MATERIAL_SIGMAS, "other_material": int((~member).sum()),
                              "other_particles": {name: table[name].to_numpy()[~member].tolist() for name in table.columns}}
        table = table[member]
    return {name: table[name].to_numpy() for name in table.columns}, record


def _predict_recording(request: PredictRequest, frames, out: Path, record_path: Path, *, progress, should_stop, log: Log) -> StepResult:
    """A recording: one table with a ``frame`` column; finished frames kept in OUT.parts/ until the table is written."""
    from napari_lbs._core.foundation import read_hologram
    from napari_lbs._core.learning import load_model
    from napari_lbs._core.recordings import predict_sequence

    work_dir = check_output_path(out.with_name(out.name + ".parts"), flag="--out", folder=True)
    background = read_hologram(request.background_path, log=log) if request.background_path else request.sequence_background
    model = load_model(request.model, device="cpu")  # each worker moves it to the device
    refine = request.refine or request.material_index_contrast is not None  # the fit measures the material
    settings = request.settings()
    if refine:
        accept = _acceptance_threshold(model.meta, request.threshold)
        settings = replace(settings, threshold=_proposal_threshold(model.meta, request.threshold))
    result = predict_sequence(frames, model, request.config, background=background, background_window=request.background_window, workers=request.workers,
                              scheduler=request.scheduler, work_dir=work_dir, settings=settings, progress=progress, should_stop=should_stop)
    particles, provenance = result.particles, dict(result.provenance)
    if refine:
        # the second look runs in this process, on the prediction's device (the workers moved their own copies there)
        looker = load_model(request.model, device=request.device) if isinstance(request.model, (str, Path)) else model
        propose = _network_proposals(looker, request.config, settings, progress=progress, should_stop=should_stop)
        fit = _fit_settings(None, request.config or model.config, device=request.device, material=request.material_index_contrast,
                            depth_prior_um=_network_depth_error_um(model.meta))
        particles, provenance["refine"] = _refined_frames(frames, particles, request.config or model.config, fit, background=background,
                                                          material=request.material_index_contrast, propose=propose, log=log, progress=progress,
                                                          should_stop=should_stop, accept_score=accept)
    _write_table(out, record_path, particles, {**provenance, "background_file": request.background_path, "particles": str(out)})
    shutil.rmtree(work_dir)
    count, done = len(result.particles["x_um"]), result.provenance["frames"]
    resumed = f"; {result.resumed} frames resumed from {work_dir}" if result.resumed else ""
    refined = _refine_summary(provenance["refine"]) if refine else ""
    return StepResult(f"found {count} particles in {done} frames in {result.seconds:.1f} s ({result.provenance['scheduler']}{resumed}){refined} -> {out} "
                      f"(provenance: {record_path})", result, (out, record_path))


# --- track ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrackRequest:
    """The particles of a recording linked into 3-D tracks.

    Attributes
    ----------
    particles_path : path
        A particle table with a ``frame`` column (CSV or ``.parquet``).
    out_path : Path
        The tracks table; its provenance beside it as ``.json``.
    search_range_um : float
        Largest displacement between two frames a particle is seen in (µm).
    axial_search_range_um : float, optional
        A separate search range along z (µm).
    memory : int
        Frames a particle may be missed and keep its track.
    replace : bool
        Replace existing outputs (the user's ``--force``, or a save dialog that asked); links, devices and FIFOs are refused regardless.
    """

    particles_path: str | Path
    out_path: Path
    _: KW_ONLY  # the data above, the options below
    search_range_um: float = 60.0
    axial_search_range_um: float | None = None
    memory: int = 0
    replace: bool = False


def track(request: TrackRequest, *, progress: ProgressCallback | None = None, should_stop: StopCallback | None = None) -> StepResult:
    """Link tracks (`link_tracks`, frame by frame: ``should_stop`` is heard between frames) and write them with the prediction's provenance."""
    import numpy as np

    from napari_lbs._core.foundation import check_table_name, read_particles, write_particles
    from napari_lbs._core.recordings import DISPLACEMENT_COLUMNS, link_tracks

    prediction_json = Path(request.particles_path).with_suffix(".json")
    out = check_table_name(check_output_path(request.out_path, flag="--out", inputs=[request.particles_path, prediction_json], force=request.replace))
    # the tracks' provenance beside them, never over the prediction's own
    provenance_json = check_output_path(out.with_suffix(".json"), flag="--out", inputs=[request.particles_path, prediction_json], force=request.replace)
    table = read_particles(request.particles_path)
    if "frame" not in table:
        raise InputError(f"{request.particles_path}: no frame column; tracks need the table of a recording (predict with several frames)")
    try:
        tracks = link_tracks(table, search_range_um=request.search_range_um, axial_search_range_um=request.axial_search_range_um, memory=request.memory,
                             progress=progress, should_stop=should_stop)
    except InputError as error:
        text = str(error)
        raise InputError(text.replace("particle table:", f"{request.particles_path}:", 1) if text.startswith("particle table:") else text) from None
    linking = {"particles": str(request.particles_path), "search_range_um": request.search_range_um, "axial_search_range_um": request.axial_search_range_um, "memory": request.memory}
    if out.suffix.lower() != ".parquet":  # a track's last detection has no displacement: an empty CSV cell (Parquet keeps NaN)
        for name in DISPLACEMENT_COLUMNS:
            tracks[name] = np.array(["" if np.isnan(value) else f"{value:.9g}" for value in tracks[name]], dtype=object)
    record = {"particles": str(out), "tracks": linking}
    if prediction_json.is_file():  # what made the detections: model, settings, frames
        try:
            record["prediction"] = json.loads(prediction_json.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError):
            record["prediction"] = None
    write_particles(out, tracks, metadata=record, force=request.replace)
    write_json(provenance_json, record)
    lengths = np.bincount(tracks["track"]) if tracks["track"].size else np.zeros(0, int)
    frames = len(np.unique(tracks["frame"]))
    return StepResult(f"linked {tracks['track'].size} particles of {frames} frames into {lengths.size} tracks (median length {np.median(lengths) if lengths.size else 0:g} frames) -> {out}",
                      tracks, (out, provenance_json))
