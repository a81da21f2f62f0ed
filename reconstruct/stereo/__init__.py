"""Stereo matching, apart from fusion: ``matching`` (a rectified pair's SGBM depth, the consistency
filter, normals) and ``depth_maps`` (every reference view's maps: CPU or CUDA back-end). The dense
stage (``reconstruct.dense``) picks the back-end and fuses the maps."""
