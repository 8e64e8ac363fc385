"""The commands behind ``blockloc``: everything that reads config files, opens sequences by name,
prints or picks defaults. ``blockloc.cli`` only parses options and calls these; core packages
(maps, registration, tracking, global_init, evaluation, datasets, sim) never import them."""
