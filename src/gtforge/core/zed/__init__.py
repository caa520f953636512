"""The ZED pair: rectification measured on board corners (rectification), the self-rectification fit (selfcal), the
disparity-scale corrections (scale_corrections)."""
