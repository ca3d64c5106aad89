"""Pictures and summaries for people: mesh and marker layout figures, stage reports."""
