"""Evaluation: replaying recorded sequences through the engine, matching ground truth, error
statistics (shared by ``sfmloc replay`` and ``sfmloc bench``)."""
