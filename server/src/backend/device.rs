//! Where the graphs run and how ONNX Runtime optimises them.

use clap::ValueEnum;

/// Graph optimisation level handed to ONNX Runtime.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum GraphOptLevel {
    Disable,
    Basic,
    Extended,
    All,
}

/// Where the graphs run: `cpu`, or `cuda` / `cuda:N` (ONNX Runtime's CUDA execution provider on
/// GPU N; needs the onnxruntime-gpu library, see `--ort-dylib`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Device {
    Cpu,
    Cuda { device_id: i32 },
}

impl std::str::FromStr for Device {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "cpu" => Ok(Device::Cpu),
            "cuda" | "gpu" => Ok(Device::Cuda { device_id: 0 }),
            other => other
                .strip_prefix("cuda:")
                .and_then(|n| n.parse::<i32>().ok())
                .filter(|&n| n >= 0)
                .map(|device_id| Device::Cuda { device_id })
                .ok_or_else(|| format!("unknown device \"{s}\" (cpu, cuda, cuda:N)")),
        }
    }
}

impl std::fmt::Display for Device {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Device::Cpu => write!(f, "cpu"),
            Device::Cuda { device_id } => write!(f, "cuda:{device_id}"),
        }
    }
}
