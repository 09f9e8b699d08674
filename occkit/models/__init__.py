"""Networks: encoders, view transforms, fusion, heads and the zoo of complete models."""
