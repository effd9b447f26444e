"""Data: the procedural scene generator, readers for the paper's data sets, the batch pipeline."""
