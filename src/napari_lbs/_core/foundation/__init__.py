"""The foundation: errors, progress and stop, files, threads and worker pools, the experiment config, validation, I/O, built-in data.

Imports nothing else of the package; every other wing stands on it. Other wings import these names from ``napari_lbs._core.foundation``, never from its
private modules; each name is imported on first use.

`_config`
    The experiment config: optics, sample volume, synthetic particles and tile size.
`_errors`
    The two refusals every layer raises: bad input and a bad experiment config.
`_files`
    Files: atomic writes, strict JSON, and reading UTF-8 text and JSON objects.
`_interrupts`
    SIGTERM and Ctrl-C as `KeyboardInterrupt`, raised where unwinding is safe.
`_io`
    Reading holograms; reading and writing stacks and particle tables.
`_lazy`
    Names a package exports, imported from their modules on first use (PEP 562).
`_pools`
    Worker processes: tasks run in a pool of one-thread processes, with progress and stop, results in task order.
`_progress`
    The one pattern for long work: ``progress(done, total)`` and ``should_stop()`` callbacks.
`_samples`
    Built-in data: the seed paper"s real 1024² hologram (MIT, see data/LICENSE-lbs-experiment.txt).
`_threads`
    How many threads this process"s numerical work uses.
`_validation`
    Input validation: every reader and entry point checks here, before any heavy work.
"""

from napari_lbs._core.foundation._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "_config": ("ExperimentConfig", "MAX_PARTICLES", "load_config", "write_config"),
        "_errors": ("ConfigError", "InputError"),
        "_files": ("atomic_path", "atomic_write_bytes", "check_target", "json_safe", "read_json_object", "write_json"),
        "_io": ("PARTICLE_COLUMNS", "as_hologram", "check_table_name", "read_hologram", "read_particles", "read_stack", "refusing_damaged_tiff", "tiff_pages", "write_particles", "write_stack"),
        "_interrupts": ("deferred_interrupts", "interruptible", "run_interruptibly"),
        "_lazy": ("lazy_exports",),
        "_pools": ("CHECK_S", "WorkerPool", "run_in_workers"),
        "_progress": ("ProgressCallback", "ReportCallback", "Steps", "StopCallback", "Stopped", "begin_phase"),
        "_samples": ("SAMPLE_PROVENANCE", "load_sample_hologram"),
        "_threads": ("available_threads", "process_threads", "size_threads", "thread_pool"),
        "_validation": ("check_calibration", "check_number", "check_dataset_manifest", "check_disk", "check_holo_params", "check_memory", "check_model_payload", "check_output_path", "check_prediction_meta", "check_resume_matches", "load_resume_state"),
    },
)
