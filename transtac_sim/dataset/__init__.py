"""Dataset generation: scene file -> dataset folder (DESIGN.md section 4), its manifest, COCO export and checks."""
