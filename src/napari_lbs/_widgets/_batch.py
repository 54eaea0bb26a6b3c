"""Step 7: a recording (folder, glob, multi-page TIFF or video) + model → Points per frame and 3-D Tracks (µm)."""

from __future__ import annotations

import glob
import re
from pathlib import Path

import numpy as np
from magicgui.widgets import ComboBox, FloatSpinBox, LineEdit, SpinBox

from napari_lbs._core import Stopped, link_tracks, open_frames, predict_sequence, sequence_background
from napari_lbs._core.recordings import BACKGROUND_MODES
from napari_lbs._layers import PlaneGrid, frame_points, recording_image, track_lines
from napari_lbs._widgets._base import StepWidget
from napari_lbs._widgets._fields import chosen, config_problem, doc_of, model_config, model_problem, path_edit
from napari_lbs._widgets._setup import file_of, model_setup

__all__ = ["BatchWidget"]


class BatchWidget(StepWidget):
    """Recording + model → Points layer with frame as napari's time axis, and a Tracks layer (trackpy), in µm."""

    title = "batch prediction"

    def __init__(self, napari_viewer) -> None:
        self.frames = path_edit(label="frames", name="frames", placeholder="a folder, run/*.tif, a multi-page TIFF or a video",
                                tooltip=f"The recording (type a folder or a glob pattern; browse picks a file): {doc_of(open_frames, 'inputs')}")
        self.model = path_edit(label="model file", name="model", filter="*.pt", value="lbs-model.pt", tooltip=doc_of(predict_sequence, "model"))
        self.config = path_edit(label="config", name="config", placeholder="empty: the model's", filter="*.toml", tooltip=doc_of(predict_sequence, "config"))
        # auto, as the command line and the API: the median only where the recording shows it holds
        # no particle (a slow particle left in it would be divided out), else each frame's flat field
        self.background = ComboBox(label="background", name="background", choices=list(BACKGROUND_MODES), value="auto",
                                   tooltip=doc_of(predict_sequence, "background"))
        self.window = SpinBox(label="background window", name="window", value=21, min=1, max=10000, tooltip=f"running background: {doc_of(sequence_background, 'window')}")
        self.device = ComboBox(label="device", name="device", choices=["auto", "cpu", "cuda"], value="auto", tooltip=doc_of(predict_sequence, "device"))
        self.workers = SpinBox(label="workers (0: threads)", name="workers", value=0, min=0, max=1024,
                               tooltip=f"{doc_of(predict_sequence, 'workers')} 0: the local threaded scheduler")
        self.scheduler = LineEdit(label="scheduler address", name="scheduler", value="",
                                  tooltip=f"{doc_of(predict_sequence, 'scheduler')} Its workers need napari-lbs and torch, not the frames. "
                                          "Empty: none; not with workers")
        self.scheduler.native.setPlaceholderText("empty: none (tcp://host:8786)")
        self.work_dir = path_edit(label="work folder", name="work_dir", mode="d", placeholder="empty: results in memory only",
                                  tooltip=f"{doc_of(predict_sequence, 'work_dir')} Empty: none. "
                                          "A stopped run started again with the same folder resumes without redoing the finished frames")
        self.work_dir.choose_btn.text = "Select folder"  # shorter than "Choose directory": room for the path in the workflow dock
        self.search_range = FloatSpinBox(label="search range µm", name="search_range_um", value=60.0, min=0.1, max=100000.0, tooltip=doc_of(link_tracks, "search_range_um"))
        self.axial_range = FloatSpinBox(label="axial search range µm (0: same)", name="axial_search_range_um", value=0.0, min=0.0, max=100000.0,
                                        tooltip=f"{doc_of(link_tracks, 'axial_search_range_um')} 0: the search range in 3-D")
        self.memory = SpinBox(label="memory (frames)", name="memory", value=0, min=0, max=10000, tooltip=doc_of(link_tracks, "memory"))
        self._resumable = False  # the running job keeps its finished frames in a work folder
        super().__init__(napari_viewer, [self.frames, self.model, self.config, self.background, self.window, self.device,
                                         self.workers, self.scheduler, self.work_dir, self.search_range, self.axial_range, self.memory])

    def problem(self):
        frames = chosen(self.frames)
        if frames is None:
            return "frames: choose a folder, a glob pattern (run/*.tif), a multi-page TIFF or a video"
        if not frames.exists():
            if not glob.has_magic(str(frames)):
                return f"frames: {frames} not found"
            if not glob.glob(str(frames)):
                return f"frames: no file matches {frames}"
        problem = model_problem(self.model) or config_problem(self.config)
        if problem:
            return problem
        scheduler = self.scheduler.value.strip()
        if scheduler and self.workers.value:
            return "workers: give either a number of local workers or a scheduler address, not both"
        if scheduler and not re.fullmatch(r"\w+://\S+:\d+", scheduler):
            return f"scheduler address: expected scheme://host:port (tcp://host:8786), got {scheduler}"
        work_dir = chosen(self.work_dir)
        return f"work folder: {work_dir} is a file, expected a folder" if work_dir is not None and work_dir.is_file() else None

    def prepare(self):
        config, warning = model_setup(chosen(self.model), model_config(self.config))
        linking = {"search_range_um": self.search_range.value, "axial_search_range_um": self.axial_range.value or None, "memory": self.memory.value}
        work_dir = chosen(self.work_dir)
        engine = {"workers": self.workers.value or None, "scheduler": self.scheduler.value.strip() or None,
                  "work_dir": str(work_dir) if work_dir is not None else None}
        self._resumable = work_dir is not None
        return str(chosen(self.frames)), chosen(self.model), config, warning, self.background.value, self.window.value, self.device.value, engine, linking

    def caution(self, job):
        return job[3]

    def phase_weights(self, job):
        return {"frames": 0.95, "tracks": 0.05}

    def work(self, job, *, progress, should_stop, report):
        frames, model, config, warning, background, window, device, engine, linking = job
        progress.phase("frames")
        result = predict_sequence([frames], model, config, background=background, background_window=window, **engine, device=device, force=warning is not None,
                                  progress=progress, should_stop=should_stop)
        progress.phase("tracks")
        return result, link_tracks(result.particles, **linking, progress=progress, should_stop=should_stop), frames, engine, linking

    def _on_errored(self, error: Exception) -> None:
        """As every step's, but a run stopped with a work folder kept its finished frames: say that running again resumes."""
        super()._on_errored(error)
        if isinstance(error, Stopped) and self._resumable:
            self._outcome = f"{error}; run again to resume"

    def show(self, outcome):
        result, tracks, source, engine, linking = outcome
        grid = PlaneGrid.of_provenance(result.provenance)
        metadata = {"provenance": result.provenance, "source": source, **engine, "linking": linking}
        frames, particles, found = result.provenance["frames"], len(tracks["x_um"]), np.unique(tracks["track"]).size
        # the recording first: results beside a recording still in pixels would mix units
        self._show_recording(source, grid, frames=frames, planes=int(result.provenance["planes_um"][2]))
        data, keywords = frame_points(tracks, grid)
        self._viewer.add_points(data, **keywords, border_color="cyan", border_width=0.15, name=f"{_short(source)} particles", metadata=metadata)
        if found:  # napari's Tracks cannot be empty
            data, keywords = track_lines(tracks, grid)
            self._viewer.add_tracks(data, **keywords, tail_length=frames, name=f"{_short(source)} tracks", metadata=metadata)
        self._viewer.dims.set_point(self._viewer.dims.ndim - 4, 0)  # the first frame
        resumed = f"; {result.resumed} frames resumed from the work folder" if result.resumed else ""
        self.done(f"{particles} particles in {frames} frames → {found} tracks in {result.seconds:.1f} s; background {result.provenance['background_used']}; {result.provenance['scheduler']}{resumed}")


    def _show_recording(self, source: str, grid: PlaneGrid, *, frames: int, planes: int) -> None:
        """Put the recording, where a reader opened it as ``(frame, row, col)``, on the results' axes: its frames in time, not in depth."""
        from napari.layers import Image

        opened = [layer for layer in self._viewer.layers if isinstance(layer, Image) and not layer.rgb and layer.ndim == 3 and layer.data.shape[0] == frames
                  and file_of(layer) is not None and Path(file_of(layer)) == Path(source).resolve()]
        for layer in opened:  # a layer cannot gain an axis: it is replaced by one with the same look
            index = self._viewer.layers.index(layer)
            data, keywords = recording_image(layer.data, grid, planes=planes)
            self._viewer.layers.remove(layer)
            added = self._viewer.add_image(data, **keywords, name=layer.name, colormap=layer.colormap, contrast_limits=layer.contrast_limits, opacity=layer.opacity,
                                           blending=layer.blending, metadata={**layer.metadata, "source": source})
            self._viewer.layers.move(self._viewer.layers.index(added), index)


def _short(source: str) -> str:
    """A recording's name for its layers: the file, folder or pattern without its folders."""
    return source.rstrip("/\\").replace("\\", "/").rsplit("/", 1)[-1]
