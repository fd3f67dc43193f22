def write_sequence(*a, **k): raise NotImplementedError
