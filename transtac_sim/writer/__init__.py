"""Writer stage: files on disk, always written atomically."""
