"""Generative priors: a frame-wise novel-view model and a video model (issue 13).

    models          which weights are in the models folder, loading them (never downloads)
    novel_view      Zero123-style novel views of the input video from other cameras
    refine          CogVideoX video-to-video refinement (generated views, predicted futures)
    lora            LoRA adapters in peft's layout (fine-tuning output, loaded with the model)
    finetune        LoRA fine-tuning of both models on multi-view captures
    random_weights  random models in the public layouts (tests, benchmarks)

diffusers, transformers and peft are imported inside functions: importing this package is cheap.
"""
