"""Context encoders: (B, R, C) observation windows with a padding mask -> (B, E) embeddings."""
