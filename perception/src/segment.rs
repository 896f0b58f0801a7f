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

/// Anything that segments RGB frames into object instances with classes.
pub trait Segmenter: Send {
    /// Segments one RGB8 frame (`width × height × 3` bytes, row-major).
    fn segment(&mut self, rgb: &[u8], width: u32, height: u32) -> Result<Segmentation, PerceptionError>;
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
        let environment = onnxruntime(&config.onnxruntime_library)?;
        let load = |e: String| PerceptionError::Model(format!("cannot load segmentation model {}: {e}", path.display()));
        let mut builder = Session::builder(&environment).map_err(|e| load(e.to_string()))?;
        if config.intra_threads > 0 {
            builder = builder.with_intra_threads(config.intra_threads).map_err(|e| load(e.to_string()))?;
        }
        let (mut builder, device) = with_provider(builder, config.execution_provider).map_err(load)?;
        let session = builder.commit_from_file(&path).map_err(|e| load(e.to_string()))?;

        let not_yolo = |why: String| {
            PerceptionError::Model(format!("segmentation model {} is not a YOLOv8-seg export: {why}", path.display()))
        };
        let input = session.inputs().first().ok_or_else(|| not_yolo("it has no input".into()))?;
        let input_name = input.name().to_string();
        let input_shape = tensor_shape(input.dtype()).ok_or_else(|| not_yolo("its input is not a tensor".into()))?;
        let model_size = match input_shape.as_slice() {
            [1, 3, h, w] if h == w && *h > 0 => *h as u32,
            other => return Err(not_yolo(format!("input shape {other:?} is not [1, 3, S, S]"))),
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
            [1, r, n] if *r > 4 && *n > 0 => (*r as usize, *n as usize),
            other => return Err(not_yolo(format!("output0 shape {other:?} is not [1, 4+C+M, N]"))),
        };
        let (mask_dim, proto_side) = match proto.as_slice() {
            [1, m, p, q] if p == q && *m > 0 && *p > 0 => (*m as usize, *p as usize),
            other => return Err(not_yolo(format!("output1 shape {other:?} is not [1, M, P, P]"))),
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
        tracing::info!(model = %path.display(), size = model_size, classes, device, "segmentation model loaded");
        Ok(Self {
            session,
            input_name,
            letterbox_size: model_size,
            classes,
            mask_dim,
            anchors,
            proto_side,
            names,
            params,
            device: device.to_string(),
            model_path: path,
        })
    }

    /// The model's square input side.
    pub fn input_size(&self) -> u32 {
        self.letterbox_size
    }

    pub fn model_path(&self) -> &Path {
        &self.model_path
    }
}

fn tensor_shape(t: &ort::value::ValueType) -> Option<Vec<i64>> {
    match t {
        ort::value::ValueType::Tensor { shape, .. } => Some(shape.iter().copied().collect()),
        _ => None,
    }
}

/// Registers the execution provider; CUDA falls back to the CPU with a warning.
fn with_provider(
    builder: ort::session::builder::SessionBuilder,
    provider: ExecutionProvider,
) -> Result<(ort::session::builder::SessionBuilder, &'static str), String> {
    match provider {
        ExecutionProvider::Cpu => Ok((builder, "cpu")),
        #[cfg(feature = "cuda")]
        ExecutionProvider::Cuda => {
            use ort::ep::ExecutionProvider as _;
            if !ort::ep::CUDA::is_available().unwrap_or(false) {
                tracing::warn!("this ONNX Runtime has no CUDA execution provider; segmentation runs on the CPU");
                return Ok((builder, "cpu"));
            }
            let mut with_cuda = builder.clone();
            match ort::ep::CUDA::default().register(&mut with_cuda) {
                Ok(()) => Ok((with_cuda, "cuda")),
                Err(e) => {
                    tracing::warn!("CUDA execution provider unavailable ({e}); segmentation runs on the CPU");
                    Ok((builder, "cpu"))
                }
            }
        }
        #[cfg(not(feature = "cuda"))]
        ExecutionProvider::Cuda => {
            tracing::warn!("stillmap was built without the `cuda` feature; segmentation runs on the CPU");
            Ok((builder, "cpu"))
        }
    }
}

impl Segmenter for YoloSegmenter {
    fn segment(&mut self, rgb: &[u8], width: u32, height: u32) -> Result<Segmentation, PerceptionError> {
        if width == 0 || height == 0 {
            return Err(PerceptionError::Input(format!("image size {width}x{height} is empty")));
        }
        let lb = Letterbox::new(width, height, self.letterbox_size);
        let data = yolo::preprocess(rgb, width, height, &lb)?;
        let s = self.letterbox_size as usize;
        let input = Tensor::from_array(([1usize, 3, s, s], data)).map_err(|e| PerceptionError::Runtime(e.to_string()))?;
        let outputs = self
            .session
            .run(ort::inputs![self.input_name.as_str() => input])
            .map_err(|e| PerceptionError::Runtime(format!("inference failed: {e}")))?;
        let (_, det) = outputs[0].try_extract_tensor::<f32>().map_err(|e| PerceptionError::Runtime(e.to_string()))?;
        let (_, proto) = outputs[1].try_extract_tensor::<f32>().map_err(|e| PerceptionError::Runtime(e.to_string()))?;
        let detections = yolo::decode_detections(det, self.anchors, self.classes, self.mask_dim, &self.params)?;
        yolo::assemble(&detections, proto, self.mask_dim, self.proto_side, &lb, width, height, &self.params, &self.names)
    }

    fn class_names(&self) -> &[String] {
        &self.names
    }

    fn device(&self) -> &str {
        &self.device
    }
}
