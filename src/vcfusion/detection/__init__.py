"""Detection stage: detectors behind one interface (oracle, our CNN, ONNX), the CNN's training and
the COCO-style box mAP."""
