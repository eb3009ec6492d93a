"""HDF5 trajectory store, dataset generation and PyG datasets."""
