"""Value types and limits with no I/O and no imports from the rest of the service: the bottom
layer every other package may use."""
