"""Data: UAPD reading, Potsdam crops, synthetic UAPD-format generation, the sample schema.

The Lightning data modules live in :mod:`dapm_lightning.data.datamodules`; the typed predict batch in
:mod:`dapm_lightning.data.unlabelled`; files written whole and checked in :mod:`dapm_lightning.data.files`; loader
workers in :mod:`dapm_lightning.data.workers`.
"""

from dapm_lightning.data.errors import DatasetError
from dapm_lightning.data.potsdam import PotsdamDataset
from dapm_lightning.data.sample import Sample
from dapm_lightning.data.synthetic import generate_uapd
from dapm_lightning.data.uapd import UAPDDataset, format_uapd_filename, parse_uapd_filename

__all__ = ["DatasetError", "PotsdamDataset", "Sample", "UAPDDataset", "format_uapd_filename", "generate_uapd",
           "parse_uapd_filename"]
