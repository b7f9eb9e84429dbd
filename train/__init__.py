"""Training and study tools for shocktwin (calibration, network training, the study).

Every model and feature comes from the ``shocktwin`` bindings (the same Rust code the
daemon runs); nothing here re-implements the twin's physics.
"""
