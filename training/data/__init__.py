"""Shape data: generation, ingest, preprocessing (paper Section 4) and sampling."""
