"""The lidar: per-ray times (timing), spinning-lidar models (model, vlp32c, carla), rays at their own
time (rays) and one stored frame (frames)."""
