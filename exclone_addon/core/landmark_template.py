"""Build-time: the bundled library's face as the landmark template (data.LANDMARK_TEMPLATE_FILE).

scripts/make_landmark_template.py writes what this computes; a test checks the shipped file is
current. Nothing here runs during a clone.
"""
from . import landmarks
from .library import load_library
from .mesh import outward_sign, vertex_normals
from .orientation import face_frame


def compute_template():
    """The bundled library's face as template: its canonical landmark positions by name, the
    outward normals of the NORMAL_PLACED ones, and its own automatic landmarks (names, vertex
    ids) found with that template: (positions, normals, (names, ids)).

    Shipped precomputed: computing them costs a second on every first clone, and the library's
    landmarks another 0.7 s on every clone from it.
    """
    lib = load_library()
    verts = lib.mesh.vertices
    tris = lib.mesh.triangles()
    frame = face_frame(verts, tris)
    ids = landmarks.heuristic_landmarks(verts, tris, frame)
    # template-only points from the iBUG annotation; points the heuristics also find keep the
    # heuristics' version, so template and target are placed by the same rule
    ids.update({name: int(lib.landmarks68[k]) for name, k in landmarks.TEMPLATE_IBUG.items()
                if name not in ids})
    q = frame.to_canonical(verts)
    template = {name: q[v] for name, v in ids.items()}
    outward = outward_sign(q, tris) * vertex_normals(q, tris)
    normals = {name: outward[ids[name]] for name in landmarks.NORMAL_PLACED if name in ids}
    return template, normals, landmarks.automatic_landmarks(verts, tris, frame, template, normals)
