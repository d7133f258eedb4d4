"""What a run is scored by: torchmetrics classes, the test pass, what each learned edge type
means."""
