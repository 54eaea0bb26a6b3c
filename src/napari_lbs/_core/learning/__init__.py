"""Synthetic data sets, the U-Net, training, prediction, peak detection and scoring.

Stands on calibration, physics and the foundation. Other wings import these names from ``napari_lbs._core.learning``, never from its
private modules; each name is imported on first use.

`_dataset`
    Better synthetic training data: random groups through HCS and Holo-processing, on disk.
`_detection`
    From network output planes to particles.
`_device_planes`
    The prediction's reconstruction planes on the network's device: back-propagation with ``torch.fft``.
`_device_samples`
    Training samples assembled where the network runs: crops, dihedral turns, targets and augmentation, batched.
`_formulations`
    The training formulations, ``focus`` and the seed's: each one's network, batches, loss and validation by detection.
`_heatmaps`
    Training targets of the ``focus`` formulation: particle-centre heatmaps, depth offsets, diameters.
`_metrics`
    Scoring reconstructed particles against a reference: one-to-one matching, ER and JI.
`_network`
    The U-Net (the seed"s, Sec. 2.3, Fig. 4, and its multi-plane variant) and the model file that carries it.
`_prediction`
    Prediction: a whole hologram → reconstruction planes → U-Net tile by tile → particles.
`_training`
    Training a network on a synthetic data set, validated by detection on held-out synthetic groups.
`_training_settings`
    How to train: `TrainingSettings`, checked when made.
"""

from napari_lbs._core.foundation import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "_dataset": ("DatasetLayout", "InputProcessing", "SyntheticDataset", "generate_dataset", "open_dataset"),
        "_metrics": ("AXIAL_TOL_UM", "LATERAL_TOL_UM", "match_particles", "score_particles", "seed_scores"),
        "_network": ("LoadedModel", "check_model_matches", "load_model", "model_mismatches", "resolve_device", "resolve_precision"),
        "_prediction": ("PredictionResult", "PredictionSettings", "check_threshold", "predict_particles", "prediction_settings"),
        "_training": ("TrainingResult", "train_model"),
        "_training_settings": ("TrainingSettings",),
    },
)
