"""The JSON schemas of an se3sync log's channels (docs/reference/log.md). The foxglove.* channels
carry Foxglove's published schemas instead (cosim/log/foxglove_schemas/)."""
from __future__ import annotations

TIME = {"type": "object", "title": "time",
        "properties": {"sec": {"type": "integer", "minimum": 0},
                       "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}}}
VEC3 = {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}

FRAME_TRANSFORMS = {
    "title": "foxglove.FrameTransforms",
    "description": "An array of FrameTransform messages",
    "type": "object",
    "properties": {
        "transforms": {
            "type": "array",
            "items": {
                "title": "foxglove.FrameTransform",
                "description": "A transform between two reference frames in 3D space",
                "type": "object",
                "properties": {
                    "timestamp": dict(TIME, description="Timestamp of transform"),
                    "parent_frame_id": {"type": "string", "description": "Name of the parent frame"},
                    "child_frame_id": {"type": "string", "description": "Name of the child frame"},
                    "translation": {
                        "title": "foxglove.Vector3",
                        "description": "Translation component of the transform",
                        "type": "object",
                        "properties": {k: {"type": "number", "description": f"{k} coordinate length"}
                                       for k in "xyz"},
                    },
                    "rotation": {
                        "title": "foxglove.Quaternion",
                        "description": "Rotation component of the transform",
                        "type": "object",
                        "properties": {k: {"type": "number", "description": f"{k} value"}
                                       for k in "xyzw"},
                    },
                },
            },
            "description": "Array of transforms",
        }
    },
}

EDGES = {
    "title": "se3sync.Edges",
    "description": "Per-edge state of the hybrid controller at a communication point",
    "type": "object",
    "properties": {
        "timestamp": TIME,
        "edges": {"type": "array", "items": {"type": "object", "properties": {
            "edge": {"type": "integer", "description": "edge number k (from 1)"},
            "positive": {"type": "integer"}, "negative": {"type": "integer"},
            "theta": {"type": "number", "description": "θ_k after the jump stage (rad)"},
            "mu_U": {"type": "number", "description": "μ_U(X̄_k, θ_k) before any jump"},
            "rot_err": {"type": "number", "description": "‖I − R̄_k‖_F"},
            "pos_err": {"type": "number", "description": "‖p̄_k‖ (m)"},
            "U": {"type": "number", "description": "U(X̄_k, θ_k)"},
            "mode": {"type": "string", "enum": ["flow", "jump"]},
        }}},
    },
}

AGENTS = {
    "title": "se3sync.Agents",
    "description": "Per-agent body velocity and applied wrench (body frame)",
    "type": "object",
    "properties": {
        "timestamp": TIME,
        "agents": {"type": "array", "items": {"type": "object", "properties": {
            "agent": {"type": "integer"},
            "omega": dict(VEC3, description="angular velocity ω_i (rad/s)"),
            "v": dict(VEC3, description="linear velocity v_i (m/s)"),
            "torque": dict(VEC3, description="τ_i (N m)"),
            "force": dict(VEC3, description="f_i (N)"),
        }}},
    },
}

LYAPUNOV = {
    "title": "se3sync.Lyapunov",
    "type": "object",
    "properties": {"timestamp": TIME,
                   "V": {"type": "number", "description": "V̄ = k_X Σ U + Σ ξᵀ𝕀ξ"},
                   "kX_U": {"type": "number", "description": "k_X Σ_k U(X̄_k, θ_k)"}},
}

JUMP = {
    "title": "se3sync.Jump",
    "type": "object",
    "properties": {"timestamp": TIME, "t": {"type": "number"}, "edge": {"type": "integer"},
                   "theta_before": {"type": "number"}, "theta_after": {"type": "number"},
                   "mu": {"type": "number"}},
}

LINK_STATS = {"title": "se3sync.LinkStats", "type": "object",
              "properties": {"timestamp": TIME}, "additionalProperties": True}

# channels whose schema is Foxglove's published one (cosim/foxglove_schemas/), by type name
FOXGLOVE = {"/tf": "FrameTransforms", "/scene": "SceneUpdate"}

SCHEMAS = {"/tf": FRAME_TRANSFORMS, "/edges": EDGES, "/agents": AGENTS, "/lyapunov": LYAPUNOV,
           "/jumps": JUMP, "/link/stats": LINK_STATS}
