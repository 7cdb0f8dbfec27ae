"""The camera: camera models, which points a frame sees (visibility), image-aligned labels, lidar
colours from pictures, and the ego-body mask with its cues."""
