"""Pure torch models: the DAPM network and its parts (never imports Lightning)."""

from dapm_lightning.models.dapm import DAPMNet, DAPMOutput
from dapm_lightning.models.encoder import Encoder

__all__ = ["DAPMNet", "DAPMOutput", "Encoder"]
