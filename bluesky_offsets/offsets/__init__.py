"""Finding the offsets: the problem and its finder methods, identifiability, the beam search, evaluation, the Bluesky finder callable."""
