"""Measurements as a dataset, whatever file holds them: a CSV of ``calib.measure.dataset``'s
format, an IPA tracker series as it comes, or a run's MCAP log. Each loader imports its reader
only when called (``acquire fit --help`` and a CSV fit never load the MCAP reader)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    from calib.measure.dataset import Dataset
    from calib.robot.model import RobotModel

log = logging.getLogger("acquire.commands.fit")

Loader = Callable[[Path, "RobotModel"], "Dataset"]


def dataset_from_csv(path: Path, model: RobotModel) -> Dataset:
    """A CSV of ``calib.measure.dataset``'s format as a dataset, or an IPA tracker series as it comes
    (``calib.measure.ipa_tracker``: recognised by its header — UR joint names and ``measurement_*``)."""
    from calib.measure.dataset import DatasetError, read_csv
    from calib.measure.ipa_tracker import JOINTS, is_ipa_series, read_ipa_series

    if is_ipa_series(path):
        if model.n_joints != len(JOINTS):
            raise DatasetError(f"{path}: an IPA tracker series of a 6-axis UR ({', '.join(JOINTS)}); the model "
                               f"{model.name!r} has {model.n_joints} axes")
        marker = model.marker_names[0]
        log.info("%s: read as an IPA tracker series (';', decimal comma, radians, Euler XYZ degrees); marker %s", path, marker)
        return read_ipa_series(path, marker=marker, sensor="tracker")
    return read_csv(path, model)


def dataset_from_run(path: Path, model: RobotModel) -> Dataset:
    """A run's MCAP log as a dataset (``acquire.record.recorder``, imported only for .mcap input)."""
    from acquire.record.recorder import dataset_from_run as load

    return load(path, model)


#: Input loaders by lower-case file suffix; each imports its reader when called.
LOADERS: dict[str, Loader] = {".csv": dataset_from_csv, ".mcap": dataset_from_run}


def load_dataset(path: Path, model: RobotModel) -> Dataset:
    """Read ``path`` with the loader for its suffix; DatasetError on unknown suffixes."""
    from calib.measure.dataset import DatasetError

    loader = LOADERS.get(path.suffix.lower())
    if loader is None:
        raise DatasetError(f"{path}: no loader for {path.suffix or 'files without a suffix'!r}; known: {sorted(LOADERS)}")
    return loader(path, model)
