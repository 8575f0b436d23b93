"""Scenes: real ones loaded from disk (datasets, one parser per format in dataparsers, the loaded
scene in scene), procedural ones generated and ray-traced here (procedural), and the committed
example request written from one of those (example)."""
