"""The paper's evaluation measures and protocol on ground truth."""
