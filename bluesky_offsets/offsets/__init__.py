"""Finding the offsets.

The problem and its finder methods, identifiability, the beam search, evaluation, the Bluesky finder callable.
"""
