"""Every file format in and out. Nothing else in cfm_fem opens files."""
