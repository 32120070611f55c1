"""File input and output: every format of ../shared/formats.md is read and written here, atomically.

    heightmaps  read_relief / write_relief: height maps (.npz, .x3p, Gwyddion, SPIP, SDF, images, ...)
    recording   read_recording / write_recording (relief-recording/1 text), read_sample / write_sample
                (relief-sample/1 JSON: plate, instrument, the files a sample consists of)
    hdf5        save_tables / load_tables / table_for: BSDF tables (relief-bsdf-table/1)
    isbsdf      export_isbsdf / read_isbsdf / import_isbsdf: the IS-BSDF text format (OpticStudio)
    radiance_xml write_radiance_xml / read_radiance_xml: the LBNL/WINDOW XML BSDF (Radiance, WINDOW)
    tables      read_table_file: any BSDF table file (.h5, IS-BSDF, XML, RPC text) as BsdfTables
    measured    read_measured / read_recording_files: measured plate BSDF files (RPC Photonics text,
                measured IS-BSDF) as recording rows in the project's frame
    atomic      atomic_path / write_text_atomic / write_bytes_atomic: the only way outputs are written
                (temporary file beside the target, then rename: a reader never sees half a file)
    oiio        the optional OpenImageIO binding (EXR / TIFF)
"""
from relief_bsdf._lazy import lazy_exports

# name -> sub-module; loaded on first use (PEP 562), so `import relief_bsdf.io.atomic` stays cheap
_EXPORTS = {
    "atomic_path": "atomic", "write_text_atomic": "atomic", "write_bytes_atomic": "atomic",
    "load_tables": "hdf5", "save_tables": "hdf5", "table_for": "hdf5",
    "read_relief": "heightmaps", "write_relief": "heightmaps",
    "export_isbsdf": "isbsdf", "import_isbsdf": "isbsdf", "read_isbsdf": "isbsdf",
    "write_radiance_xml": "radiance_xml", "read_radiance_xml": "radiance_xml", "read_table_file": "tables",
    "Recording": "recording", "read_recording": "recording", "write_recording": "recording",
    "Sample": "recording", "PlateSpec": "recording", "InstrumentSpec": "recording",
    "read_sample": "recording", "write_sample": "recording",
    "read_measured": "measured", "read_recording_files": "measured",
}
__all__ = list(_EXPORTS)

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS, globals())
