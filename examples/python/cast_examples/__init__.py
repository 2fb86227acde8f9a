"""The scene-description demo's Python components (configs/demo.yaml)."""
