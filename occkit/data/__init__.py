"""Data pipeline: nuScenes tables to an index, datasets of typed samples, transforms, collation."""
