"""What a run writes for its users: clip tables, segment export, predictions, figures, the results
card."""
