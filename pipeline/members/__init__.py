"""The forecasters of the published ensemble and its references, one interface (``base``)."""
