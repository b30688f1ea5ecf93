"""Diagnosis of simulation-vs-recording mismatches: calibrate, locate, attribute, model, advise."""
