"""Motion data: the HumanML3D representation, importers, HDF5 shards and the training Dataset."""
