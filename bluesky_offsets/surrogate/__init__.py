"""The neural surrogate of the twin: the network, its datasets, training and evaluation."""
