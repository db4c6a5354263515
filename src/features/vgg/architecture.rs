//! VGG19's convolutional part up to `relu5_4` (SPEC §4), as one table: the layer sequence,
//! the convolutions' names and torchvision indices, and the five taps.
//!
//! Plain constants and no imports, so `build.rs` (which writes the ONNX graph burn-import
//! turns into Burn code), the weight loader and the tests all read this one file.

/// Output channels of the 16 convolutions (3×3, stride 1, padding 1, each followed by a
/// ReLU), in order; `None` marks a 2×2 max-pool of stride 2.
pub const LAYERS: [Option<usize>; 20] = [
    Some(64),
    Some(64),
    None,
    Some(128),
    Some(128),
    None,
    Some(256),
    Some(256),
    Some(256),
    Some(256),
    None,
    Some(512),
    Some(512),
    Some(512),
    Some(512),
    None,
    Some(512),
    Some(512),
    Some(512),
    Some(512),
];

/// The convolutions in order, with the names users know them by.
pub const CONV_NAMES: [&str; 16] = [
    "conv1_1", "conv1_2", "conv2_1", "conv2_2", "conv3_1", "conv3_2", "conv3_3", "conv3_4",
    "conv4_1", "conv4_2", "conv4_3", "conv4_4", "conv5_1", "conv5_2", "conv5_3", "conv5_4",
];

/// torchvision's `vgg19.features` index of each of the 16 convolutions.
pub const TORCHVISION_INDEX: [usize; 16] =
    [0, 2, 5, 7, 10, 12, 14, 16, 19, 21, 23, 25, 28, 30, 32, 34];

/// The five taps of SPEC §4, finest first (`TAPS[s]` has `1/2^s` of the input's size): the
/// name and the index (0-based) of the convolution whose ReLU is tapped.
pub const TAPS: [(&str, usize); 5] = [
    ("relu1_2", 1),
    ("relu2_2", 3),
    ("relu3_4", 7),
    ("relu4_4", 11),
    ("relu5_4", 15),
];

/// `[out, in, 3, 3]` of each of the 16 convolutions.
pub fn conv_shapes() -> Vec<[usize; 4]> {
    let mut shapes = Vec::with_capacity(16);
    let mut channels = 3;
    for out in LAYERS.iter().flatten() {
        shapes.push([*out, channels, 3, 3]);
        channels = *out;
    }
    shapes
}

/// Channels of each tap.
pub fn tap_channels() -> [usize; 5] {
    let shapes = conv_shapes();
    TAPS.map(|(_, conv)| shapes[conv][0])
}
