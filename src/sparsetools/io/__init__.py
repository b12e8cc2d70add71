"""File formats only: point clouds, calibrations, images and depth PNGs, nuScenes tables."""
