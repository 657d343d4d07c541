"""camloc: localize a robot in a known landmark map from g2o odometry and camera observations.

    >>> import camloc
    >>> dataset = camloc.load(camloc.bundled_dataset("grid-small"))
    >>> result = camloc.localize(dataset)

Heavy modules are imported on first use so that ``camloc --help`` stays instant.
"""

from __future__ import annotations

__version__ = "0.1.0"

# LocalizerConfig's groups of options, as the library writes them: LocalizerConfig(beam=BeamOptions(width=8))
_OPTION_GROUPS = ("BeamOptions", "BestFriendsOptions", "JcbbOptions", "RecheckOptions", "ViewOptions")

__all__ = ["__version__", "load", "localize", "LocalizerConfig", *_OPTION_GROUPS, "bundled_dataset"]


def __getattr__(name: str):
    if name == "load":
        from camloc.g2o import read_g2o

        return read_g2o
    if name == "localize":
        from camloc.localizer import localize

        return localize
    if name in ("LocalizerConfig", *_OPTION_GROUPS):
        from camloc import localizer_config

        return getattr(localizer_config, name)
    if name == "bundled_dataset":
        from camloc.bundled import bundled_dataset

        return bundled_dataset
    raise AttributeError(f"module 'camloc' has no attribute {name!r}")
