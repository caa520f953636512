"""The dataset folder on disk: its files and views, split lists, resume stamps, scene-writer locks, worker caches, \
and each scene's ground-truth arrays."""
