"""Reading scenes and writing results: OBJ/MTL, glTF, textures, exported meshes."""
