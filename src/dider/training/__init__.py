"""The training shell: the LightningModule around the network, its callbacks, run folders,
checkpoints and random state."""
