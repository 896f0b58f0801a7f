//! Instance segmentation: the [`Segmenter`] trait, its per-frame output, and
//! [`YoloSegmenter`], a YOLOv8-seg ONNX model on ONNX Runtime (`ort`).

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use ort::session::Session;
use ort::value::Tensor;

use crate::PerceptionError;
use crate::config::{ExecutionProvider, SegmentationConfig};
use crate::yolo::{self, DecodeParams, Letterbox};

/// Instance id of pixels that belong to no instance.
pub const NO_INSTANCE: u16 = 0;
/// Class id of pixels that belong to no instance.
pub const NO_CLASS: u16 = u16::MAX;

/// One detected object instance.
#[derive(Debug, Clone, PartialEq)]
pub struct Instance {
    /// 1-based id, as stored in [`Segmentation::instance_map`].
    pub id: u16,
    pub class_id: u16,
    pub class_name: String,
    /// Class score, 0–1.
    pub score: f32,
    /// x0, y0, x1, y1 in frame pixels.
    pub bbox: [f32; 4],
    /// Pixels of the frame assigned to this instance.
    pub pixels: u32,
}

/// A frame's segmentation: an instance id per pixel and the instance list.
#[derive(Debug, Clone, PartialEq)]
pub struct Segmentation {
    pub width: u32,
    pub height: u32,
    /// Row-major, [`NO_INSTANCE`] or an [`Instance::id`].
    pub instance_map: Vec<u16>,
    pub instances: Vec<Instance>,
}

impl Segmentation {
    /// A segmentation with no instances.
    pub fn empty(width: u32, height: u32) -> Self {
        Self { width, height, instance_map: vec![NO_INSTANCE; width as usize * height as usize], instances: Vec::new() }
    }

    pub fn instance(&self, id: u16) -> Option<&Instance> {
        // Ids are dense and 1-based in segmenter output, but warping or filtering may
        // drop some: fall back to a search.
        self.instances.get(usize::from(id).wrapping_sub(1)).filter(|i| i.id == id).or_else(|| self.instances.iter().find(|i| i.id == id))
    }

    /// Class id per pixel ([`NO_CLASS`] outside instances).
    pub fn class_map(&self) -> Vec<u16> {
        let lut = self.lookup(|i| i.class_id, NO_CLASS);
        self.instance_map.iter().map(|&id| lut[usize::from(id)]).collect()
    }

    /// Class score per pixel (0 outside instances).
    pub fn score_map(&self) -> Vec<f32> {
        let lut = self.lookup(|i| i.score, 0.0);
        self.instance_map.iter().map(|&id| lut[usize::from(id)]).collect()
    }

    fn lookup<T: Copy>(&self, f: impl Fn(&Instance) -> T, none: T) -> Vec<T> {
        let max = self.instances.iter().map(|i| usize::from(i.id)).max().unwrap_or(0);
        let mut lut = vec![none; max + 1];
        for i in &self.instances {
            lut[usize::from(i.id)] = f(i);
        }
        lut
    }
}

/// One RGB8 frame to segment (`width × height × 3` bytes, row-major).
#[derive(Debug, Clone, Copy)]
pub struct RgbFrame<'a> {
    pub rgb: &'a [u8],
    pub width: u32,
    pub height: u32,
}

/// Anything that segments RGB frames into object instances with classes.
pub trait Segmenter: Send {
    /// Segments one RGB8 frame (`width × height × 3` bytes, row-major).
    fn segment(&mut self, rgb: &[u8], width: u32, height: u32) -> Result<Segmentation, PerceptionError>;
    /// Segments several frames, one result per frame in order. A segmenter that
    /// cannot batch runs them one by one (the default); results equal
    /// [`segment`](Self::segment)'s either way.
    fn segment_batch(&mut self, frames: &[RgbFrame<'_>]) -> Result<Vec<Segmentation>, PerceptionError> {
        frames.iter().map(|f| self.segment(f.rgb, f.width, f.height)).collect()
    }
    /// Most frames one [`segment_batch`](Self::segment_batch) call runs together (1: no batching).
    fn max_batch(&self) -> usize {
        1
    }
    /// Runs every batch shape that batches of up to `max_batch` frames will use once,
    /// so that no frame pays a device's first-run cost (cuDNN's convolution search
    /// for each new input shape: up to a second per shape). Returns the shapes run.
    /// A segmenter with nothing to warm does nothing (the default).
    fn warm_up(&mut self, max_batch: usize) -> Result<Vec<usize>, PerceptionError> {
        let _ = max_batch;
        Ok(Vec::new())
    }
    /// Class names, indexed by class id.
    fn class_names(&self) -> &[String];
    /// Where inference runs ("cpu", "cuda").
    fn device(&self) -> &str;
}

/// The ONNX Runtime environment is process-wide: the library is loaded once.
static ORT_ENVIRONMENT: OnceLock<Result<ort::environment::Environment, String>> = OnceLock::new();

fn onnxruntime(library: &str) -> Result<ort::environment::Environment, PerceptionError> {
    ORT_ENVIRONMENT
        .get_or_init(|| {
            let path = if library.is_empty() { std::env::var("ORT_DYLIB_PATH").unwrap_or_default() } else { library.to_string() };
            if path.is_empty() {
                return Err("no ONNX Runtime library: set perception.segmentation.onnxruntime_library or ORT_DYLIB_PATH".into());
            }
            if !Path::new(&path).is_file() {
                return Err(format!("ONNX Runtime library {path} does not exist"));
            }
            let builder = ort::init_from(&path).map_err(|e| format!("cannot load ONNX Runtime from {path}: {e}"))?;
            builder.with_name("stillmap").build().map_err(|e| format!("cannot start ONNX Runtime from {path}: {e}"))
        })
        .clone()
        .map_err(PerceptionError::Runtime)
}

/// YOLOv8-seg (Ultralytics ONNX export) on ONNX Runtime.
pub struct YoloSegmenter {
    session: Session,
    /// With padded batches: one session per batch shape above 1 (made by
    /// [`Segmenter::warm_up`]), so that no session ever sees its input shape change.
    /// ONNX Runtime's CUDA provider plans every convolution again (cuDNN) each time a
    /// session's input shape differs from its previous run: measured on an H200,
    /// 0.4–1.6 s per change, so batches alternating between 2 and 4 frames took
    /// seconds. One shape per session plans once.
    shape_sessions: Vec<(usize, Session)>,
    /// Makes those sessions (the same provider and options as `session`).
    config: SegmentationConfig,
    input_name: String,
    letterbox_size: u32,
    classes: usize,
    mask_dim: usize,
    anchors: usize,
    proto_side: usize,
    names: Vec<String>,
    params: DecodeParams,
    device: String,
    model_path: PathBuf,
    /// The model takes any batch size (its input's first dimension is symbolic).
    dynamic_batch: bool,
    /// Pad each batch to the next power of two ([`batch_shape`]): on a GPU every new
    /// input shape costs a convolution-algorithm search, so batches use a few shapes
    /// that [`Segmenter::warm_up`] runs at start-up. On by default for GPU providers
    /// (on a CPU the padding would be computed for nothing).
    pad_batches: bool,
}

/// The input batch a batch of `frames` frames runs as when batches are padded: the
/// next power of two (1, 2, 4, 8, …), so that at most ⌈log₂ max_batch⌉ + 1 shapes occur.
pub fn batch_shape(frames: usize) -> usize {
    frames.max(1).next_power_of_two()
}

/// The padded batch shapes batches of 1 to `max_batch` frames use.
pub fn batch_shapes(max_batch: usize) -> Vec<usize> {
    let top = batch_shape(max_batch);
    std::iter::successors(Some(1usize), |b| (*b < top).then_some(b * 2)).collect()
}

impl YoloSegmenter {
    /// Loads the model named in `config`; every problem with the file is an error
    /// naming it (missing, not ONNX, not a YOLOv8-seg export, size mismatch).
    pub fn new(config: &SegmentationConfig) -> Result<Self, PerceptionError> {
        let path = PathBuf::from(&config.model_path);
        if config.model_path.is_empty() {
            return Err(PerceptionError::Model("no segmentation model path configured (perception.segmentation.model_path)".into()));
        }
        if !path.is_file() {
            return Err(PerceptionError::Model(format!("segmentation model {} does not exist", path.display())));
        }
        let load = |e: String| PerceptionError::Model(format!("cannot load segmentation model {}: {e}", path.display()));
        let (session, device) = open_session(config).map_err(|e| match e {
            OpenError::Runtime(e) => e,
            OpenError::Provider(why) => PerceptionError::Model(why),
            OpenError::Load(why) => load(why),
        })?;

        let not_yolo =
            |why: String| PerceptionError::Model(format!("segmentation model {} is not a YOLOv8-seg export: {why}", path.display()));
        let input = session.inputs().first().ok_or_else(|| not_yolo("it has no input".into()))?;
        let input_name = input.name().to_string();
        let input_shape = tensor_shape(input.dtype()).ok_or_else(|| not_yolo("its input is not a tensor".into()))?;
        // A fixed batch of 1, or a symbolic batch (-1: deploy/make-batched-model.py).
        let (model_size, dynamic_batch) = match input_shape.as_slice() {
            [b @ (1 | -1), 3, h, w] if h == w && *h > 0 => (*h as u32, *b == -1),
            other => return Err(not_yolo(format!("input shape {other:?} is not [1, 3, S, S] or [batch, 3, S, S]"))),
        };
        if config.input_size != 0 && config.input_size != model_size {
            return Err(PerceptionError::Model(format!(
                "perception.segmentation.input_size is {} but model {} takes {model_size}×{model_size}",
                config.input_size,
                path.display()
            )));
        }
        let outputs = session.outputs();
        if outputs.len() != 2 {
            return Err(not_yolo(format!("it has {} outputs, expected 2 (detections, mask prototypes)", outputs.len())));
        }
        let det = tensor_shape(outputs[0].dtype()).ok_or_else(|| not_yolo("output0 is not a tensor".into()))?;
        let proto = tensor_shape(outputs[1].dtype()).ok_or_else(|| not_yolo("output1 is not a tensor".into()))?;
        let (rows, anchors) = match det.as_slice() {
            [1 | -1, r, n] if *r > 4 && *n > 0 => (*r as usize, *n as usize),
            other => return Err(not_yolo(format!("output0 shape {other:?} is not [batch, 4+C+M, N]"))),
        };
        let (mask_dim, proto_side) = match proto.as_slice() {
            [1 | -1, m, p, q] if p == q && *m > 0 && *p > 0 => (*m as usize, *p as usize),
            other => return Err(not_yolo(format!("output1 shape {other:?} is not [batch, M, P, P]"))),
        };
        if rows <= 4 + mask_dim {
            return Err(not_yolo(format!("output0 has {rows} rows, too few for {mask_dim} mask coefficients")));
        }
        let classes = rows - 4 - mask_dim;
        let names = match session.metadata().ok().and_then(|m| m.custom("names")) {
            Some(text) => yolo::parse_class_names(&text)?,
            None => (0..classes).map(|c| format!("class{c}")).collect(),
        };
        if names.len() != classes {
            return Err(not_yolo(format!("its metadata names {} classes but output0 carries {classes}", names.len())));
        }
        let params = DecodeParams {
            score_threshold: config.score_threshold,
            nms_iou_threshold: config.nms_iou_threshold,
            mask_threshold: config.mask_threshold,
            max_instances: config.max_instances,
        };
        let pad_batches = dynamic_batch && config.execution_provider != ExecutionProvider::Cpu && device != "cpu";
        tracing::info!(model = %path.display(), size = model_size, classes, device, dynamic_batch, pad_batches, "segmentation model loaded");
        Ok(Self {
            session,
            shape_sessions: Vec::new(),
            config: config.clone(),
            input_name,
            letterbox_size: model_size,
            classes,
            mask_dim,
            anchors,
            proto_side,
            names,
            params,
            device,
            model_path: path,
            dynamic_batch,
            pad_batches,
        })
    }

    /// Pads batches to [`batch_shape`] (default: on for GPU providers with a batching
    /// model). Results do not depend on it.
    pub fn set_batch_padding(&mut self, on: bool) {
        self.pad_batches = on && self.dynamic_batch;
    }

    /// Whether the model takes batches of any size.
    pub fn dynamic_batch(&self) -> bool {
        self.dynamic_batch
    }

    /// Runs the model on letterboxed frames stacked as one `[B, 3, S, S]` batch and
    /// decodes each frame's slice of the outputs.
    fn run_batch(&mut self, frames: &[RgbFrame<'_>]) -> Result<Vec<Segmentation>, PerceptionError> {
        let s = self.letterbox_size as usize;
        let mut data = Vec::with_capacity(frames.len() * 3 * s * s);
        let mut boxes = Vec::with_capacity(frames.len());
        for f in frames {
            if f.width == 0 || f.height == 0 {
                return Err(PerceptionError::Input(format!("image size {}x{} is empty", f.width, f.height)));
            }
            let lb = Letterbox::new(f.width, f.height, self.letterbox_size);
            data.extend(yolo::preprocess(f.rgb, f.width, f.height, &lb)?);
            boxes.push(lb);
        }
        // Padding frames are zeros; their outputs are not decoded.
        let batch = if self.pad_batches { batch_shape(frames.len()) } else { frames.len() };
        data.resize(batch * 3 * s * s, 0.0);
        let input = Tensor::from_array(([batch, 3, s, s], data)).map_err(|e| PerceptionError::Runtime(e.to_string()))?;
        let session = match self.shape_sessions.iter_mut().find(|(shape, _)| *shape == batch) {
            Some((_, session)) => session,
            None => &mut self.session,
        };
        let outputs = session
            .run(ort::inputs![self.input_name.as_str() => input])
            .map_err(|e| PerceptionError::Runtime(format!("inference failed: {e}")))?;
        let (_, det) = outputs[0].try_extract_tensor::<f32>().map_err(|e| PerceptionError::Runtime(e.to_string()))?;
        let (_, proto) = outputs[1].try_extract_tensor::<f32>().map_err(|e| PerceptionError::Runtime(e.to_string()))?;
        let det_len = (4 + self.classes + self.mask_dim) * self.anchors;
        let proto_len = self.mask_dim * self.proto_side * self.proto_side;
        if det.len() != batch * det_len || proto.len() != batch * proto_len {
            return Err(PerceptionError::Runtime(format!(
                "model returned {} detection and {} prototype values for a batch of {batch}, expected {} and {}",
                det.len(),
                proto.len(),
                batch * det_len,
                batch * proto_len
            )));
        }
        let mut out = Vec::with_capacity(batch);
        for (i, (f, lb)) in frames.iter().zip(&boxes).enumerate() {
            let det = &det[i * det_len..(i + 1) * det_len];
            let proto = &proto[i * proto_len..(i + 1) * proto_len];
            let detections = yolo::decode_detections(det, self.anchors, self.classes, self.mask_dim, &self.params)?;
            out.push(yolo::assemble(&detections, proto, self.mask_dim, self.proto_side, lb, f.width, f.height, &self.params, &self.names)?);
        }
        Ok(out)
    }

    /// The model's square input side.
    pub fn input_size(&self) -> u32 {
        self.letterbox_size
    }

    pub fn model_path(&self) -> &Path {
        &self.model_path
    }
}

enum OpenError {
    /// ONNX Runtime itself cannot be loaded.
    Runtime(PerceptionError),
    /// The execution provider cannot run (the message names the way out).
    Provider(String),
    /// ONNX Runtime could not load the file.
    Load(String),
}

/// One ONNX Runtime session of `config`'s model on its execution provider, and the
/// device it runs on.
fn open_session(config: &SegmentationConfig) -> Result<(Session, String), OpenError> {
    let environment = onnxruntime(&config.onnxruntime_library).map_err(OpenError::Runtime)?;
    let mut builder = Session::builder(&environment).map_err(|e| OpenError::Load(e.to_string()))?;
    if config.intra_threads > 0 {
        builder = builder.with_intra_threads(config.intra_threads).map_err(|e| OpenError::Load(e.to_string()))?;
    }
    let (mut builder, device) = with_provider(builder, config).map_err(OpenError::Provider)?;
    let session = builder.commit_from_file(&config.model_path).map_err(|e| OpenError::Load(e.to_string()))?;
    Ok((session, device))
}

fn tensor_shape(t: &ort::value::ValueType) -> Option<Vec<i64>> {
    match t {
        ort::value::ValueType::Tensor { shape, .. } => Some(shape.iter().copied().collect()),
        _ => None,
    }
}

/// Registers the configured execution provider. A GPU provider that cannot be
/// registered (this ONNX Runtime has none, or its CUDA/cuDNN libraries are missing)
/// is an error naming the problem, unless `fallback_to_cpu` is set: then the CPU,
/// with a warning. Returns the device inference runs on ("cpu", "cuda:0", "tensorrt:0").
fn with_provider(
    builder: ort::session::builder::SessionBuilder,
    config: &SegmentationConfig,
) -> Result<(ort::session::builder::SessionBuilder, String), String> {
    use ort::ep::ExecutionProvider as _;
    let device_id = config.device_id;
    let mut gpu = builder.clone();
    let registered = match config.execution_provider {
        ExecutionProvider::Cpu => return Ok((builder, "cpu".into())),
        ExecutionProvider::Cuda => {
            ort::ep::CUDA::default().with_device_id(device_id).register(&mut gpu).map(|()| format!("cuda:{device_id}"))
        }
        ExecutionProvider::Tensorrt => {
            let cache = &config.tensorrt_cache_dir;
            let trt = ort::ep::TensorRT::default()
                .with_device_id(device_id)
                .with_engine_cache(true)
                .with_engine_cache_path(cache)
                .with_timing_cache(true)
                .with_timing_cache_path(cache);
            // CUDA second: nodes TensorRT does not take run there, not on the CPU.
            trt.register(&mut gpu)
                .and_then(|()| ort::ep::CUDA::default().with_device_id(device_id).register(&mut gpu))
                .map(|()| format!("tensorrt:{device_id}"))
        }
    };
    let name = config.execution_provider.name();
    match registered {
        Ok(device) => Ok((gpu, device)),
        Err(e) if config.fallback_to_cpu => {
            tracing::warn!("execution provider {name} unavailable ({e}); segmentation runs on the CPU (fallback_to_cpu)");
            Ok((builder, "cpu".into()))
        }
        Err(e) => Err(format!(
            "perception.segmentation.execution_provider = \"{name}\" cannot run: {}. Install the GPU build of \
             ONNX Runtime and its CUDA libraries (make gpu-deps) and point ORT_DYLIB_PATH at it, or set \
             perception.segmentation.fallback_to_cpu = true to run on the CPU",
            e.to_string().trim_end_matches('.')
        )),
    }
}

impl Segmenter for YoloSegmenter {
    fn segment_batch(&mut self, frames: &[RgbFrame<'_>]) -> Result<Vec<Segmentation>, PerceptionError> {
        if self.dynamic_batch && frames.len() > 1 {
            return self.run_batch(frames);
        }
        frames.iter().map(|f| self.segment(f.rgb, f.width, f.height)).collect()
    }

    fn max_batch(&self) -> usize {
        if self.dynamic_batch { usize::MAX } else { 1 }
    }

    fn warm_up(&mut self, max_batch: usize) -> Result<Vec<usize>, PerceptionError> {
        if !self.pad_batches {
            return Ok(Vec::new());
        }
        let shapes = batch_shapes(max_batch);
        let black = vec![0u8; 64 * 48 * 3];
        for &b in &shapes {
            if b > 1 && !self.shape_sessions.iter().any(|(shape, _)| *shape == b) {
                let (session, _) = open_session(&self.config).map_err(|e| match e {
                    OpenError::Runtime(e) => e,
                    OpenError::Provider(why) | OpenError::Load(why) => PerceptionError::Model(format!(
                        "cannot load segmentation model {} for batches of {b}: {why}",
                        self.model_path.display()
                    )),
                })?;
                self.shape_sessions.push((b, session));
            }
            let frames = vec![RgbFrame { rgb: &black, width: 64, height: 48 }; b];
            let t = std::time::Instant::now();
            self.run_batch(&frames)?;
            tracing::debug!(batch = b, ms = t.elapsed().as_secs_f64() * 1e3, "segmentation warm-up");
        }
        Ok(shapes)
    }

    fn segment(&mut self, rgb: &[u8], width: u32, height: u32) -> Result<Segmentation, PerceptionError> {
        let mut out = self.run_batch(&[RgbFrame { rgb, width, height }])?;
        out.pop().ok_or_else(|| PerceptionError::Runtime("the model returned no result".into()))
    }

    fn class_names(&self) -> &[String] {
        &self.names
    }

    fn device(&self) -> &str {
        &self.device
    }
}
