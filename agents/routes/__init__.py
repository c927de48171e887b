"""Synthesis routes: reaction templates (RDKit), a stock of building blocks, and the search for routes."""
