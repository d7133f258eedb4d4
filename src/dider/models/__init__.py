"""The relational VAE as a plain ``nn.Module`` and its plugins (encoder, prior, duration, decoder),
with the loss terms it is trained by; the LightningModule around it is
:mod:`dider.training.module`."""
