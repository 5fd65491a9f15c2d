"""Export: checkpoint -> verified ONNX artefact for a target profile (`export_artefact`)."""
