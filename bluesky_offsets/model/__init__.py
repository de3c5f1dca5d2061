"""The calibrated model: the one measurement, the model state, the one fit engine, the misfit and the diagnosis of missing effects."""
