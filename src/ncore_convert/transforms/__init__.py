"""Pure, vectorised numpy transforms, by subject: ``lidar/``, ``camera/`` and ``objects/``; the
shared modules (geometry, time base, noise, sampling, CARLA frames) stay at the top."""
