"""Point labels (static / shifting / deforming) and the frame's quality signal without
ground truth."""
