"""Build-time only: our own converters from the pretrained weights' source formats to ONNX. Nothing at
serving time imports these."""
