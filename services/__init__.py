"""The FastAPI gateway and the operator dashboard of the BRDFusion rendering service."""
