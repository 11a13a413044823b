"""Fitting what is learned from a collection beyond the pipeline's own stages (the SVM bank's training)."""
