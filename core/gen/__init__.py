"""Learned generative models of BRDFusion (paper Sec. 3.2-3.3): ONNX contracts and runtime, EDM sampling and
SDEdit, small U-Nets, the OIDN / diffusion denoiser backends, the physically fitted lighting prior,
and the training scaffolding. See each module's docstring for shapes, ranges and frames."""
