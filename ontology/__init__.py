"""Ontology: semantic labels, their translation to local labels, and label search."""
