"""The calibrated model.

The one measurement, the model state, the one fit engine, the misfit and the diagnosis of missing effects.
"""
