"""Index extraction: raw bogie accelerations to on-board Top6/Align10 indices (paper 3.2)."""
