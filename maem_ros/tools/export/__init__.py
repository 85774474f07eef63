"""Getting poses out: maem-export (``export``: TRC, C3D, CSV for biomechanics tools) and
maem-foxglove (``foxglove_view``: a live Foxglove view of the graph or of bags)."""
