"""Reference implementations (plain numpy/scipy) the package's kernels are tested against; never shipped."""
