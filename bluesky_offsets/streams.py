"""Named random streams: every use of a user's seed draws from a stream of its own, named here.

Two uses then never share numbers by accident, and a new use takes a name, not an arithmetic offset.
The offsets never change, so a seed gives the same numbers in every version.

>>> stream(0, "demo.ioc_noise")
2
>>> stream(5, "diagnosis.fresh_rays", draw=1)
209463
"""

from __future__ import annotations

from bluesky_offsets.errors import InputError

#: each stream's offset from the seed it is drawn from (distinct primes where the uses sit close)
OFFSETS: dict[str, int] = {
    "demo.hidden_offsets": 1,          # the demo's hidden offsets
    "demo.ioc_noise": 2,               # the simulated IOC's frame noise
    "demo.beam_optimizer": 11,         # the beam optimization's starts and rays
    "diagnosis.fits": 7919,            # the diagnosis's fits and detection limits, apart from the offsets fit
    "diagnosis.fresh_rays": 104729,    # fresh rays no fit traced, one block per draw (times 1 + draw)
    "fit.posterior_starts": 15_485_863,  # the fit's starts drawn from its posterior
    "fit.posterior_samples": 32_452_843,  # the noise and prior draws that move posterior samples onto the frames
    "fit.posterior_sample_rays": 49_979_687,  # each posterior sample's model rays
    "grid.photons": 31,                # which of a grid source's rays a trace's photons are
    "noise_floor.second_trace": 10_000_019,  # the second of two independent traces of each configuration
    "optimizer.posterior_draws": 1,    # the focus's spread over draws of the posterior
    "training.epoch_order": 1,         # the surrogate's training order, apart from its initial weights
    "surrogate_check.uniform": 1,      # the surrogate check's uniform draws, apart from its screened ones
}

#: the default seed of the model's traces in a comparison (the same rays for every model version)
MODEL_SEED = 777


def stream(seed: int, name: str, *, draw: int = 0) -> int:
    """The seed of stream ``name`` drawn from ``seed``.

    ``draw`` is the how-many-th block of a stream that yields one per draw.
    """
    if name not in OFFSETS:
        raise InputError(f"no random stream {name!r}; known: {sorted(OFFSETS)}")
    return int(seed) + OFFSETS[name] * (1 + int(draw))
