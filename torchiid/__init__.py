"""torchiid: intrinsic image decomposition with semantic hierarchical priors."""
