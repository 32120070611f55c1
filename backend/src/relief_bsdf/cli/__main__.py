from relief_bsdf.cli import entry

entry()
