"""Models: field maps and field models, multipoles, the bench and its kinematics, the Hall probe,
GUM-S1 machinery, recordings and ISO 230-2. Arrays in, arrays out; no files, no printing.
"""
