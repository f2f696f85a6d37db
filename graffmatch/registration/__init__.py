"""Registration layer: closed-form line/plane/point least squares and ICP refinement."""
