"""Lightning layer: the LightningModule, the loss, callbacks, teacher forcing, checkpointing, viewpoint analysis."""
