"""Reading and writing the formats sfmloc exchanges with other tools (COLMAP models,
pose lists, images and videos)."""
