"""Pictures the API serves: a frame's overlay and top-down map (routes), gathered from stored rows and encoded as
PNG (service); the drawing is service.render's."""
