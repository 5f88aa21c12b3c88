"""Data edge: conventions, datasets, EXR import and export."""
