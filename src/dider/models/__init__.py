"""The relational VAE (one LightningModule) and its plugins: encoder, prior, duration, decoder."""
