"""Networks: encoders, view transforms, fusion, heads and the three architectures (config, model, benchmark stages;
their zoo entries are in :mod:`occkit.zoo`)."""
