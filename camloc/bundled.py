"""The small simulated datasets shipped inside the package (``camloc/data/*.g2o``).

They are package data, found through ``importlib.resources`` wherever camloc is installed (an
editable checkout, a wheel in site-packages), never beside the source tree or the working
directory. ``camloc/data/README.md`` says how each was generated.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from camloc.errors import ConfigError

BUNDLED_DATASETS = ("grid-small", "smooth3d-clutter", "pixel-2cam")
DEFAULT_DATASET_NAME = "grid-small"


def bundled_dataset(name: str = DEFAULT_DATASET_NAME) -> Path:
    """The path of a bundled dataset, e.g. ``camloc.load(camloc.bundled_dataset("grid-small"))``.

    Parameters
    ----------
    name : one of ``BUNDLED_DATASETS``, with or without the ``.g2o`` suffix.

    Returns
    -------
    The file's path inside the installed package (camloc is installed as plain files, not
    zipped, so the resource is a real file).

    Raises
    ------
    ConfigError : ``name`` is not a bundled dataset.
    """
    stem = name.removesuffix(".g2o")
    if stem not in BUNDLED_DATASETS:
        raise ConfigError(f"expected a bundled dataset ({', '.join(BUNDLED_DATASETS)}), found {name!r}")
    return Path(str(resources.files("camloc").joinpath("data", f"{stem}.g2o")))


def resolve_dataset(given: str | Path) -> Path:
    """A dataset argument as a path: ``given`` itself when it names a file, else the bundled
    dataset of that name (``camloc run pixel-2cam`` from an installed camloc, where
    ``camloc/data/`` is not beside the working directory), else ``given`` unchanged (the reader
    then says the file is missing)."""
    path = Path(given)
    if not path.exists() and path.parent == Path(".") and path.name.removesuffix(".g2o") in BUNDLED_DATASETS:
        return bundled_dataset(path.name)
    return path
